"""Experiments whose results the docs pages report: the yardstick, drives, the paper, the variance mask."""
