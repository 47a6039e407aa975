"""``python -m proxycodec.cli``: the command line, as the ``proxycodec`` script runs it (``proxycodec batch`` runs
its tasks so)."""

from .main import main

main()
