"""``python -m perscli``: the same as the ``perscli`` command."""

from perscli.cli.main import main

if __name__ == "__main__":
    main()
