"""``python -m btmission``: the same as the ``btmission`` command."""

from btmission.cli.launch import main

if __name__ == "__main__":
    main()
