"""Execute notebooks in place, so they are stored with their outputs (figures show on GitHub).

    python notebooks/execute.py                    # every notebook in this folder
    python notebooks/execute.py 06_real_data.ipynb

Run it from an installed checkout (``pip install -e '.[test]'``) after changing a notebook or
the code it calls, and commit the result. Each notebook runs in a fresh kernel with its folder
as the working directory; the time it took is printed. Figures are stored as PNG at 72 dpi
(`plt.rcParams["figure.dpi"]` in each notebook) to keep the files small.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import nbclient
import nbformat

HERE = Path(__file__).resolve().parent


def main(names: list[str]) -> None:
    # The kernel inherits this: tqdm's note that ipywidgets is missing is not worth storing.
    os.environ["PYTHONWARNINGS"] = "ignore:IProgress not found"
    paths = [HERE / n for n in names] if names else sorted(HERE.glob("*.ipynb"))
    for path in paths:
        nb = nbformat.read(path, as_version=4)
        start = time.perf_counter()
        nbclient.NotebookClient(
            nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}
        ).execute()
        nbformat.write(nb, path)
        print(f"{path.name}: {time.perf_counter() - start:.0f} s, {path.stat().st_size / 1e3:.0f} kB")


if __name__ == "__main__":
    main(sys.argv[1:])
