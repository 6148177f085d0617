"""``python -m pidlab``: the same command line as ``pidlab``."""

from pidlab.cli import main

main()
