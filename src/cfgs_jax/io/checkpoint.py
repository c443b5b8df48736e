"""Checkpoints of long runs: a pytree's leaves plus a JSON metadata record in one npz, written
atomically. The reader checks the format tag and the leaf count against a template pytree;
``Checkpoint`` is one stage's file with the identity of the computation it belongs to (its settings,
sizes, inputs), which a resume must match."""

from __future__ import annotations

import dataclasses
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


def _differences(saved, expected, prefix: str) -> list[tuple[str, object, object]]:
    """(dotted key, saved value, expected value) for every key of ``expected`` whose value ``saved`` does
    not hold; dict values are compared key by key."""
    if isinstance(saved, dict) and isinstance(expected, dict):
        out = []
        for k, v in expected.items():
            out += _differences(saved.get(k), v, f"{prefix}.{k}" if prefix else str(k))
        return out
    return [] if saved == expected else [(prefix, saved, expected)]


def require_identity(
    path: str | Path, saved: dict, expected: dict, *, what: str, restart: str, fields: dict | None = None
) -> None:
    """Refuse a checkpoint whose ``saved`` meta differs from ``expected`` in any of its keys (InputError
    naming each difference as ``key: saved → expected``, nested keys dotted; ``what`` names the
    computation it belongs to, ``restart`` what deleting it restarts). ``fields`` maps a top-level key to the
    configuration table it holds (``{"config": "refine"}``), so the error names the first differing field
    as the user writes it (``refine.steps``)."""
    bad = _differences(saved, expected, "")
    if not bad:
        return
    head, *rest = bad[0][0].split(".")
    field = ".".join([fields[head], *rest]) if fields and head in fields and rest else None
    shown = ", ".join(f"{k}: {_short(a)} → {_short(b)}" for k, a, b in bad[:6]) + (", …" if len(bad) > 6 else "")
    raise InputError(
        f"the checkpoint belongs to another {what} (it differs in {shown})",
        path=path,
        field=field,
        fix=f"resume with the original model and settings, or delete it to restart the {restart}",
    )


def _short(value) -> str:
    text = json.dumps(value, default=str) if not isinstance(value, str) else value
    return text if len(text) <= 40 else text[:37] + "..."


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """One stage's resumable state: the file at ``path`` (``format`` its tag) and the ``identity`` of the
    computation that writes it, a JSON-able dict saved in its metadata which a resume must match
    (``require_identity``: ``what`` names the computation, ``restart`` what deleting the file restarts,
    ``fields`` the configuration table behind a key). ``defaults[key]``: what a checkpoint written before a
    setting existed was written at: for a dict, the values of the settings under ``identity[key]``; else
    the value of ``identity[key]`` itself."""

    path: Path
    format: str
    identity: dict
    what: str
    restart: str
    defaults: dict = dataclasses.field(default_factory=dict)
    fields: dict = dataclasses.field(default_factory=dict)

    def exists(self) -> bool:
        return Path(self.path).is_file()

    def meta(self) -> dict:
        """The metadata alone (no arrays read, no identity checked)."""
        return read_meta(self.path, format=self.format, leaves=False)[0]

    def load(self, template) -> tuple[object, dict, list[np.ndarray]]:
        """(the state shaped as ``template``, the metadata, the arrays saved after the state's leaves),
        refused with InputError unless the file was written by a computation of this identity."""
        meta, arrays = read_meta(self.path, format=self.format)
        saved = meta | {
            k: d | meta.get(k, {}) if isinstance(d, dict) else meta.get(k, d) for k, d in self.defaults.items()
        }
        require_identity(self.path, saved, self.identity, what=self.what, restart=self.restart, fields=self.fields)
        n = jax.tree_util.tree_structure(template).num_leaves
        return restore_tree(self.path, arrays[:n], template), meta, list(arrays[n:])

    def save(self, state, meta: dict, extra=()) -> Path:
        """Write ``state``'s leaves, then the ``extra`` arrays, with the identity and ``meta`` (atomic)."""
        return save_tree(self.path, (state, *extra), self.identity | meta, format=self.format)
