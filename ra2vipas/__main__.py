"""``python -m ra2vipas``: the ``ra2vipas`` command."""

from ra2vipas.cli.launch import main

if __name__ == "__main__":
    main()
