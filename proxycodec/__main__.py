"""``python -m proxycodec``: the command line (``proxycodec.cli.main``)."""

from .cli.main import main

main()
