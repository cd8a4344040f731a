"""The ``official`` decoder against the official InstaGraM export's own function, on random graphs.

    python benchmarks/official_decoder.py --official /work/.mirror/juyebshin+InstaGraM/repo --graphs 1000

Reads ``vectorize_graph`` (and its ``onehot_encoding``) from ``postprocess/vectorize.py`` of a local
clone of juyebshin/InstaGraM at the commit given (default 2b978e4, the published state), runs it on
random adjacency matrices built from chains (some closed, some edges one-sided, a class per chain
with noise, padding) and compares its polylines, confidences and classes with
``postprocess_batch(..., decoder="official")``. Prints the number of graphs, of official instances
and of mismatches. Nothing of the official code is stored here; it is read from the clone at run time.
"""

from __future__ import annotations

import argparse
import subprocess

import numpy as np
import torch

from instagram_hdmap.geometry import BEVGrid
from instagram_hdmap.postprocess import postprocess_batch


def official_vectorize_graph(repo: str, commit: str):
    source = subprocess.run(["git", "-C", repo, "show", f"{commit}:postprocess/vectorize.py"], check=True,
                            capture_output=True, text=True).stdout
    parts = source[source.index("def onehot_encoding("):source.index("def onehot_encoding_spread")]
    parts += source[source.index("def vectorize_graph("):]
    namespace = {"np": np, "torch": torch}
    exec(compile(parts, "vectorize.py", "exec"), namespace)  # the reference, read from the clone at run time
    return namespace["vectorize_graph"]


def random_graph(rng: np.random.Generator) -> dict:
    N = int(rng.integers(2, 40))
    n_real = int(rng.integers(2, N + 1))
    mask = torch.zeros(N, dtype=torch.bool)
    mask[:n_real] = True
    order = rng.permutation(n_real)
    scores = np.full((N + 1, N + 1), -4.0) + rng.normal(size=(N + 1, N + 1))
    classes = rng.integers(0, 3, size=N)
    k = 0
    while k < n_real:
        chain = order[k:k + int(rng.integers(1, 8))]
        k += len(chain)
        classes[chain] = rng.integers(0, 3)
        for a, b in zip(chain[:-1], chain[1:]):
            scores[a, b] = scores[b, a] = 2 + rng.normal()
            if rng.random() < 0.2:
                scores[a, b] = -3  # one-sided
        if len(chain) > 2 and rng.random() < 0.3:
            scores[chain[0], chain[-1]] = scores[chain[-1], chain[0]] = 2  # closed
        scores[chain[[0, -1]], N] = 1.5
    logits = np.full((N, 3), -2.0)
    logits[np.arange(N), classes] = 1.0
    logits += rng.normal(size=(N, 3)) * 0.7
    return {"pred_log_assignment": torch.tensor(scores, dtype=torch.float32).log_softmax(1)[None],
            "pred_vertices_px": torch.tensor(rng.integers(0, 200, size=(N, 2)), dtype=torch.float32)[None],
            "pred_vertex_mask": mask[None], "pred_vertex_scores": torch.rand(1, N),
            "pred_class_log_probs": torch.tensor(logits, dtype=torch.float32).log_softmax(1)[None]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--official", required=True, help="a local clone of juyebshin/InstaGraM")
    ap.add_argument("--commit", default="2b978e4")
    ap.add_argument("--graphs", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    from instagram_hdmap.benchmark import check_counts

    check_counts(ap, args, graphs=1)
    vectorize_graph = official_vectorize_graph(args.official, args.commit)
    grid = BEVGrid(-30.0, 30.0, -15.0, 15.0, 0.15, 8)  # the official export's metres: u * 0.15 - 29.925
    rng = np.random.default_rng(args.seed)
    instances = mismatches = 0
    for _ in range(args.graphs):
        out = random_graph(rng)
        ours = postprocess_batch(out, grid, 0.1, decoder="official")[0]
        coords, confidences, types = vectorize_graph(out["pred_vertices_px"][0], out["pred_log_assignment"][0],
                                                     out["pred_class_log_probs"][0].T,
                                                     out["pred_vertex_mask"][0, :, None].float(), 0.1, 0.1)
        ref = [(np.asarray(c) * 0.15 - np.array([29.925, 14.925]), f, t) for c, f, t in zip(coords, confidences, types)]
        instances += len(ref)
        same = len(ref) == len(ours) and all(
            np.allclose(r[0], o["pts"], atol=1e-5) and abs(r[1] - o["score"]) < 1e-5 and r[2] == o["label"]
            for r, o in zip(ref, ours))
        mismatches += not same
    print(f"graphs {args.graphs}, official instances {instances}, mismatches {mismatches}")


if __name__ == "__main__":
    from instagram_hdmap.benchmark import script_main

    script_main(main)
