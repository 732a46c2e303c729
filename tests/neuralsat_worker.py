"""NeuralSAT's command line under the Python of its own environment (.venv-neuralsat, made
by ``make neuralsat``), for tests/test_neuralsat.py; this module imports nothing of kpstudy.

``.venv-neuralsat/bin/python tests/neuralsat_worker.py ARGS`` runs NeuralSAT 0.2.17's
``main.py`` with ``ARGS`` (``--net``, ``--spec``, ``--result_file``, …). Its wheel
installs a package ``src`` whose modules import each other as top-level modules (``from
helper.network.read_onnx import …``), so ``main.py`` runs with its own folder first on
``sys.path`` (this file's folder, tests/, taken off it). Its ONNX importer imports
torchvision for the ``NonMaxSuppression`` operator alone, and torchvision's PyPI wheels,
CUDA builds, do not load beside the CPU build of torch 2.13.0: an empty module stands in
(an exported instance has no such operator; a graph with one would fail at that node).
"""

from __future__ import annotations

import importlib.metadata
import runpy
import sys
import types
from pathlib import Path


def main() -> None:
    script = Path(importlib.metadata.distribution("neuralsat").locate_file("src/main.py"))
    sys.modules.setdefault("torchvision", types.ModuleType("torchvision"))
    sys.path[0] = str(script.parent)
    sys.argv = [str(script), *sys.argv[1:]]
    runpy.run_path(str(script), run_name="__main__")


if __name__ == "__main__":
    main()
