"""``python -m data_tools.reproduce_paper`` runs ``enmi-reproduce-paper``: the paper's Fig. simPerformance.

Run from the repository root, it uses the clone's ``enmi_torch`` whether or not it is installed.
"""

from enmi_torch.cli.reproduce_paper import main

if __name__ == "__main__":
    main()
