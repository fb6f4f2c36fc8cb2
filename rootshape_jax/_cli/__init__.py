"""The ``rootshape`` command line (also ``python -m rootshape_jax``).

Every subcommand reads roots (RSML files, folders of them, scanned images, or built-in
synthetic roots), runs one analysis and writes CSV tables, PNG figures and RSML files into an
output folder. Mistakes in the input (a missing path, an unreadable file, a bad option value)
end with one line on stderr and a non-zero exit code, never a Python traceback (``--debug``
shows it).

Modules: `_parser` (argparse), `_inputs` (reading files and folders, preparing the
population), `_steps` (the analyses and the subcommands), `_report` (the output folder: CSV,
figures, RSML, index.html), `_main` (entry point, JAX configuration, errors).
"""

from ._main import configure_jax as configure_jax, main as main
