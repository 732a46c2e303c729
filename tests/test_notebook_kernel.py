"""The study notebooks' kernels: their own diagnostics go to a log file, not the terminal."""

from __future__ import annotations

import subprocess
import sys


def test_a_notebook_kernels_own_stderr_goes_to_its_log_file(tmp_path):
    """IPKernel's log (what it prints when Ctrl-C stops a notebook, say) lands in the
    ``kernel_manager`` log; the cell's own output stays in the executed notebook."""
    script = f"""
from pathlib import Path
import nbformat, papermill
from kpstudy.study.reproduction import _ipc_kernel, kernel_manager
nb = nbformat.v4.new_notebook()
nb.cells = [nbformat.v4.new_code_cell(
    "get_ipython().kernel.log.error('kernel-side noise 7d1f'); print('cell output 7d1f')"
)]
folder = Path(r"{tmp_path}")
nbformat.write(nb, folder / "in.ipynb")
papermill.execute_notebook(
    str(folder / "in.ipynb"), str(folder / "out.ipynb"), kernel_name="python3",
    progress_bar=False, config=_ipc_kernel(str(folder)),
    kernel_manager_class=kernel_manager(folder / "kernel.log"),
)
"""
    run = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    assert "kernel-side noise 7d1f" in (tmp_path / "kernel.log").read_text()
    assert "kernel-side noise 7d1f" not in run.stderr + run.stdout
    assert "cell output 7d1f" in (tmp_path / "out.ipynb").read_text()
