"""``python -m proxycodec.bench --worker KIND JSON``: one benchmark step in a process of its own (``runner``)."""

import sys

from .runner import main

sys.exit(main())
