"""``python -m oapcal`` runs the command-line interface."""

from oapcal.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
