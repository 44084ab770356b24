"""Reading the torch files of our runs (bppo and learned-estimator models) without unpickling."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from auv_follow_env._files import check_size

__all__ = ["load_torch_file"]


def load_torch_file(path: str | Path, what: str) -> Any:
    """``torch.load(path, weights_only=True)`` (tensors and plain containers only, nothing
    unpickled), or a one-line ValueError naming the file and ``what`` it should be,
    never torch's advice to load it with ``weights_only=False``."""
    import zipfile

    import torch

    path = check_size(path, "model")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path} is not {what}: not a zip archive (torch's file format)")
    try:
        return torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 (zipfile, pickle and torch errors alike)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        if "weights_only" in first or "Weights only load failed" in first:
            first = "it holds objects other than tensors and plain containers, which are never unpickled"
        raise ValueError(f"{path} is not {what}: {type(exc).__name__}: {first[:200]}") from None
