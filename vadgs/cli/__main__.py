"""``python -m vadgs.cli``: the ``vadgs`` command."""

from vadgs.cli import main

raise SystemExit(main())
