"""The paper's figures and plotted points."""
