"""``python -m data_tools.make_pairs`` runs ``enmi-make-pairs``: write synthetic local/prior pairs (``--help``).

Run from the repository root, it uses the clone's ``enmi_torch`` whether or not it is installed.
"""

from enmi_torch.cli.make_pairs import main

if __name__ == "__main__":
    main()
