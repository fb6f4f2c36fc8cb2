"""``python -m rootshape_jax``: the ``rootshape`` command line."""

from rootshape_jax._cli import main

raise SystemExit(main())
