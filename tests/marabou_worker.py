"""Marabou in a child process, for tests/test_marabou.py.

Marabou 2.0.0 once ignored ``timeoutInSeconds`` on an exported instance: its solver runs
in C++ and cannot be interrupted from Python. So the tests solve in a spawned child that
:class:`MarabouProcess` kills when it overruns; this module imports nothing but maraboupy
in the child.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import time


def serve(conn) -> None:
    """The child: answer ``(onnx, vnnlib, seconds)`` jobs with ``(code, x, y, seconds)``,
    ``code`` Marabou's answer (``'sat'``, ``'unsat'``, ``'TIMEOUT'``, …) or ``'error: …'``,
    ``x`` and ``y`` the ONNX input and output of a ``sat`` answer (lists in C order; ``y``
    as Marabou's assignment has it), else None; ``None`` ends the child."""
    import warnings

    warnings.filterwarnings("ignore")  # "Tensorflow parser is unavailable"
    from maraboupy import Marabou

    while (job := conn.recv()) is not None:
        onnx_path, vnnlib_path, seconds = job
        start = time.perf_counter()
        try:
            network = Marabou.read_onnx(onnx_path)
            options = Marabou.createOptions(
                verbosity=0, timeoutInSeconds=int(seconds), numBlasThreads=1
            )
            code, values, _ = network.solve(
                filename=os.devnull, verbose=False, options=options, propertyFilename=vnnlib_path
            )
            x = y = None
            if code == "sat":
                x = [float(values[v]) for v in network.inputVars[0].flatten()]
                y = [float(values[v]) for v in network.outputVars[0].flatten()]
        except Exception as exc:  # noqa: BLE001 - reported to the test as the answer
            code, x, y = f"error: {type(exc).__name__}: {exc}", None, None
        conn.send((code, x, y, time.perf_counter() - start))


class MarabouProcess:
    """One child running :func:`serve`; :meth:`solve` kills and replaces it when it does
    not answer within the job's seconds plus ``grace``."""

    def __init__(self, grace: float = 20.0) -> None:
        self.grace = grace
        self._context = multiprocessing.get_context("spawn")
        self._start()

    def _start(self) -> None:
        self._conn, child = self._context.Pipe()
        self._process = self._context.Process(target=serve, args=(child,), daemon=True)
        self._process.start()
        child.close()

    def solve(self, onnx_path, vnnlib_path, seconds: int):
        """``(code, x, y, seconds)`` as :func:`serve` answers; ``('hung', None, None, s)``
        when the child had to be killed."""
        start = time.perf_counter()
        self._conn.send((str(onnx_path), str(vnnlib_path), int(seconds)))
        if self._conn.poll(seconds + self.grace):
            return self._conn.recv()
        self._kill()
        self._start()
        return "hung", None, None, time.perf_counter() - start

    def _kill(self) -> None:
        self._process.kill()
        self._process.join(10)
        self._conn.close()

    def close(self) -> None:
        with contextlib.suppress(OSError, BrokenPipeError):
            self._conn.send(None)
        self._process.join(10)
        if self._process.is_alive():
            self._kill()
        else:
            self._conn.close()
