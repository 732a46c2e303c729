"""Your instance for other verifiers: ONNX + VNN-LIB, the VNN-COMP exchange format.

Run from the repository root: ``.venv/bin/python docs/examples/export_vnnlib.py [OUT]``
(seconds on one core; ``OUT`` defaults to ``results/examples/export``). It exports the
network and hull of ``own_model.py`` (copy both files), then runs the ONNX graph on
points of its input box with onnxruntime.
"""

import sys

import numpy as np
import onnxruntime
import torch
from own_model import hull_images, make_model

from kpstudy.models.preprocess import to_model_input
from kpstudy.verify import ArgmaxSpec, ConvexHull, export_instance, read_vnnlib_polytope


def main(out: str) -> None:
    model, images = make_model(), hull_images()
    x = to_model_input(images, size=model.input_size)
    with torch.no_grad():
        heatmaps = model(x[:1])[0]
    targets = heatmaps.flatten(1).argmax(1).tolist()
    spec = ArgmaxSpec([heatmaps[0].numel()] * len(heatmaps), targets)

    # model.onnx: input u in [0, 1]^n (n perturbed images), mapped exactly onto the hull
    # inside the graph; output: each keypoint's worst margin. spec.vnnlib: the violation,
    # "some margin <= 0" (a VNN-COMP verifier's unsat means the property holds).
    files = export_instance(out, model, ConvexHull(x), spec)
    disjuncts = read_vnnlib_polytope(files["vnnlib"])["disjuncts"]

    session = onnxruntime.InferenceSession(str(files["onnx"]))
    u = np.random.default_rng(0).uniform(0, 1, (64, files["n_inputs"])).astype(np.float32)
    margins = np.concatenate([session.run(None, {files["input_name"]: p[None]})[0] for p in u])
    print(
        f"wrote {files['onnx']} ({files['n_inputs']} inputs, {files['n_outputs']} outputs) "
        f"and {files['vnnlib']} ({len(disjuncts)} disjuncts)"
    )
    print(
        f"onnxruntime on 64 points of the box: least margin {margins.min():.3g}, "
        f"{'every keypoint kept' if margins.min() > 0 else 'a violation'}"
    )


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "results/examples/export")
