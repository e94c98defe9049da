"""Simulated rig captures of fabrics, reconstructed by psmini's default pipeline, kept in a cache.

Shared by the fabric benchmarks (``fabric_family.py``, ``fabric_recognition.py --protocol shift``): each capture
is rendered from a :class:`data_synth.fabrics.Fabric` and its capture conditions, reconstructed, and the depth,
mask, albedo, slopes and one LED image are written to ``cache/<name>-<tag>.npz`` (through a temporary file), the
tag a hash of the code (not the docstrings or layout) and configuration a reconstruction depends on, so that a
stale entry is never read.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._ledger import REPO  # noqa: E402

# What a cached reconstruction depends on besides the fabric and its conditions: the renderer's and the
# pipeline's code.
CACHE_SOURCES = ("data_synth/rig.py", "psmini/render.py", "psmini/pipeline.py", "psmini/nearlight.py",
                 "psmini/normals.py", "psmini/flatfield.py", "psmini/lights.py", "psmini/geometry.py",
                 "psmini/_tensor.py", "psmini/integrate/least_squares.py", "psmini/integrate/poisson.py",
                 "psmini/integrate/bilateral.py", "psmini/integrate/fourier.py", "psmini/integrate/_dct.py")


@dataclass
class Reconstructed:
    """One reconstructed capture (batch of one, CPU tensors) and one of its LED images."""

    depth: torch.Tensor
    mask: torch.Tensor
    albedo: torch.Tensor
    p: torch.Tensor
    q: torch.Tensor
    image: np.ndarray  # (H, W) in [0, 1]: the capture's image under ``image_led``


def code_digest(path: Path) -> bytes:
    """What a Python source computes, without its docstrings, comments and layout: the dump of its syntax tree with
    the docstrings removed (a docstring or a line break changes no reconstruction); the bytes for another file."""
    import ast

    text = path.read_bytes()
    if path.suffix != ".py":
        return text
    tree = ast.parse(text)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]  # type: ignore[attr-defined]
    return ast.dump(tree).encode()


def sources_digest(names: tuple[str, ...]) -> str:
    """A hash of the code of the repository's files ``names`` (:func:`code_digest`; a missing file by its name)."""
    digest = hashlib.sha1()
    for name in names:
        path = REPO / name
        digest.update(code_digest(path) if path.is_file() else name.encode())
    return digest.hexdigest()[:12]


def source_tag(config: Any, extra: dict | None = None) -> str:
    """A hash of the code of :data:`CACHE_SOURCES`, the reconstruction configuration and ``extra`` (e.g. the rig)."""
    digest = hashlib.sha1(json.dumps(config.to_dict(), sort_keys=True, default=str).encode())
    digest.update(json.dumps(extra or {}, sort_keys=True, default=str).encode())
    digest.update(sources_digest(CACHE_SOURCES).encode())
    return digest.hexdigest()[:12]


def reconstruct_capture(key: str, make, cache: Path | None, tag: str, config: Any,
                        image_led: int = 0) -> Reconstructed:
    """The reconstruction of the capture ``make()`` returns, from the cache when there.

    Args:
        key: the capture's name in the cache (unique for its fabric and conditions).
        make: a function returning ``(sample, capture)``: the :class:`psmini.io.Sample` and the
            :class:`data_synth.rig.SyntheticCapture` (called only on a cache miss).
        cache: the cache folder, or None.
        tag: :func:`source_tag` of the configuration.
        config: the :class:`psmini.config.ReconstructionConfig`.
        image_led: which LED's image is kept.
    """
    from psmini.pipeline import reconstruct

    path = cache / f"{key}-{tag}.npz" if cache is not None else None
    if path is not None and path.is_file():
        data = np.load(path)
        return Reconstructed(torch.from_numpy(data["depth"]), torch.from_numpy(data["mask"]),
                             torch.from_numpy(data["albedo"]), torch.from_numpy(data["p"]).float(),
                             torch.from_numpy(data["q"]).float(), data["image"])
    sample, capture = make()
    rec = reconstruct(sample, config)
    out = Reconstructed(rec.depth[:1].cpu(), rec.mask[:1].cpu(), rec.albedo[:1].cpu(), rec.p[:1].cpu(),
                        rec.q[:1].cpu(), capture.images[image_led].cpu().numpy())
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.stem}.tmp.npz")
        np.savez(temporary, depth=out.depth.numpy(), mask=out.mask.numpy(), albedo=out.albedo.numpy(),
                 p=out.p.numpy().astype(np.float16), q=out.q.numpy().astype(np.float16), image=out.image)
        temporary.replace(path)
    return out
