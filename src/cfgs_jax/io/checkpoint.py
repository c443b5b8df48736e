"""Checkpoints of long runs: a pytree's leaves plus a JSON metadata record in one npz, written
atomically. The reader checks the format tag and the leaf count against a template pytree; callers
check their own metadata (configuration, sizes) before trusting the state."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cfgs_jax.errors import InputError
from cfgs_jax.io.atomic import atomic_file


def save_tree(path: str | Path, tree, meta: dict, *, format: str) -> Path:
    """Write ``tree``'s leaves (``leaf_0000`` …) and ``meta`` (+ format, leaf count) atomically."""
    leaves = jax.tree_util.tree_leaves(tree)
    meta = meta | {"format": format, "num_leaves": len(leaves)}
    arrays = {f"leaf_{i:04d}": np.asarray(x) for i, x in enumerate(leaves)}
    with atomic_file(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, __meta__=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)
    return Path(path)


def read_meta(path: str | Path, *, format: str, leaves: bool = True) -> tuple[dict, list[np.ndarray]]:
    """(meta, leaf arrays) of a checkpoint of ``format`` (no arrays read unless ``leaves``); unreadable or
    foreign files raise InputError."""
    try:
        with np.load(path) as data:
            meta = json.loads(bytes(data["__meta__"]).decode())
            arrays = [data[f"leaf_{i:04d}"] for i in range(meta["num_leaves"])] if leaves else []
    except (OSError, KeyError, ValueError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable checkpoint ({exc})", path=path, fix="delete it to start over") from exc
    if meta.get("format") != format:
        raise InputError(f"not a {format} checkpoint", path=path, field="format", fix="delete it to start over")
    return meta, arrays


def restore_tree(path: str | Path, arrays: list[np.ndarray], template):
    """The pytree of ``template``'s structure holding ``arrays`` (from ``read_meta``)."""
    treedef = jax.tree_util.tree_structure(template)
    if treedef.num_leaves != len(arrays):
        raise InputError("checkpoint layout does not match this version", path=path, fix="delete it to start over")
    return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(a) for a in arrays])


def require_identity(path: str | Path, saved: dict, expected: dict, *, what: str, restart: str) -> None:
    """Refuse a checkpoint whose ``saved`` meta differs from ``expected`` in any of its keys (InputError
    naming them; ``what`` names the computation it belongs to, ``restart`` what deleting it restarts)."""
    bad = [k for k, v in expected.items() if saved.get(k) != v]
    if bad:
        raise InputError(
            f"the checkpoint belongs to another {what} (differs in {', '.join(bad)})",
            path=path,
            fix=f"resume with the original model and settings, or delete it to restart the {restart}",
        )
