"""Checks of the test suite itself."""
