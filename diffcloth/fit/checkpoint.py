"""Fit checkpoints: one .npz (+ .json sidecar) layout for every fitting loop, and resuming."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffcloth.io.media import to_jsonable

__all__ = ["CHECKPOINT_FORMAT", "load_checkpoint", "pack_tree", "save_checkpoint", "unpack_tree"]

#: version of the checkpoint layout written by `save_checkpoint`.
CHECKPOINT_FORMAT = 2


def pack_tree(prefix: str, tree) -> dict[str, np.ndarray]:
    """A pytree's leaves as {prefix/0000: array, ...} (tree_leaves order), for `save_checkpoint`."""
    return {
        f"{prefix}/{i:04d}": np.asarray(leaf)
        for i, leaf in enumerate(jax.tree_util.tree_leaves(tree))
    }


def unpack_tree(leaves: Sequence[np.ndarray], like):
    """Rebuild a pytree shaped like `like` from its saved leaves (see `pack_tree`); checks that the
    number, shapes and dtypes of the leaves match (a checkpoint of another optimizer fails here)."""
    ref, treedef = jax.tree_util.tree_flatten(like)
    if len(ref) != len(leaves):
        raise ValueError(
            f"checkpoint: the saved solver state has {len(leaves)} leaves, this optimizer's has "
            f"{len(ref)} (was it written by another optimizer or parameter set?)"
        )
    out = []
    for i, (a, b) in enumerate(zip(ref, leaves, strict=True)):
        if np.shape(a) != np.shape(b):
            raise ValueError(
                f"checkpoint: solver state leaf {i} has shape {np.shape(b)}, expected {np.shape(a)}"
            )
        out.append(jnp.asarray(b, dtype=jnp.asarray(a).dtype))
    return jax.tree_util.tree_unflatten(treedef, out)


def save_checkpoint(path, arrays: Mapping[str, Any], meta: Mapping[str, Any]) -> str:
    """Write a fit checkpoint: `path` (.npz, the arrays) and a .json sidecar (`meta`).

    The layout any fit loop can use (keys are "group/name"): "step" (evaluations done),
    "raw/", "params/", "best/", "last_finite/" (name -> value of the best start), "state/raw/"
    (the current raw values, with the start axis for a multistart fit), "opt_state/" (the
    optimizer or solver state pytree, `pack_tree`), "history/" (loss, params/NAME, grad_norm/NAME,
    wall) and "tracker/" (the loop's stopping state). Written to a temporary file and renamed, so a
    checkpoint on disk is always complete.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()})
    os.replace(tmp, path)
    side = path.with_suffix(".json")
    side_tmp = side.with_name(side.name + ".tmp")
    side_tmp.write_text(json.dumps(to_jsonable(dict(meta)), indent=2, allow_nan=False) + "\n")
    os.replace(side_tmp, side)
    return str(path)


def load_checkpoint(path) -> dict[str, Any]:
    """Read a fit checkpoint (.npz, and its .json sidecar when present).

    Returns {"step", "raw", "params", "best", "last_finite", "opt_state", "state", "history",
    "tracker", "meta"}: dict entries map names to arrays; opt_state is the list of optimizer-state
    leaves (tree_leaves order, rebuild with `unpack_tree`); "history" holds "loss", "wall" and
    the dicts "params" and "grad_norm"; "meta" the sidecar's JSON (statuses, messages, names).
    """
    path = Path(path)
    out: dict[str, Any] = {
        "raw": {}, "params": {}, "best": {}, "last_finite": {}, "opt_state": [], "state": {},
        "history": {"params": {}, "grad_norm": {}}, "tracker": {}, "meta": {},
    }  # fmt: skip
    try:
        with open(path, "rb") as fh, np.load(fh) as z:  # (np.load(path) leaks it on a bad file)
            for key in sorted(z.files):
                if key == "step":
                    out["step"] = int(z[key])
                    continue
                if "/" not in key:
                    raise ValueError(f"unexpected entry {key!r}")
                group, name = key.split("/", 1)
                if group == "opt_state":
                    out["opt_state"].append(z[key])
                elif group in ("state", "tracker", "history") and "/" in name:
                    sub, leaf = name.split("/", 1)
                    out[group].setdefault(sub, {})[leaf] = z[key]
                elif group in out and isinstance(out[group], dict):
                    out[group][name] = z[key]
                else:
                    raise ValueError(f"unexpected entry {key!r}")
    except FileNotFoundError:
        raise ValueError(f"cannot read checkpoint {str(path)!r}: no such file") from None
    except Exception as err:  # noqa: BLE001  (zipfile, zlib, pickle, EOF: all name the file)
        raise ValueError(
            f"cannot read checkpoint {str(path)!r}: it is truncated, damaged or not a diffcloth "
            f"checkpoint ({type(err).__name__}: {err})"
        ) from None
    side = path.with_suffix(".json")
    if side.exists():
        try:
            meta = json.loads(side.read_text())
        except (OSError, ValueError) as err:
            raise ValueError(
                f"cannot read the checkpoint's sidecar {str(side)!r}: it is truncated or damaged "
                f"({type(err).__name__}: {err}); without it, --init-from can start a new fit "
                "from the .npz"
            ) from None
        if not isinstance(meta, dict):
            raise ValueError(
                f"the checkpoint's sidecar {str(side)!r} is not a JSON object (damaged?)"
            )
        out["meta"] = meta
    return out


def _as_checkpoint(resume):
    if resume is None or isinstance(resume, Mapping):
        return resume
    return load_checkpoint(resume)


def _restore(ck, raw, opt_state, names, n, steps, tr):
    """Raw values, optimizer state and tracker from a `load_checkpoint` dict (for resume=)."""
    meta = ck.get("meta", {})
    saved = meta.get("names")
    if saved is not None and list(saved) != list(names):
        raise ValueError(f"resume: the checkpoint fits {saved}, this fit {names}")
    if meta.get("starts", n) != n:
        raise ValueError(f"resume: the checkpoint has {meta.get('starts')} starts, this fit {n}")
    if "raw" not in ck.get("state", {}) or not ck.get("tracker"):
        raise ValueError("resume: the checkpoint has no loop state (written by an older version?)")
    done = int(ck["step"])
    if done > steps + 1:
        raise ValueError(
            f"resume: the checkpoint is at step {done - 1}, beyond steps={steps}; raise steps"
        )
    new_raw = {}
    for k in names:
        a = np.asarray(ck["state"]["raw"][k])
        if a.shape != tuple(raw[k].shape):
            raise ValueError(
                f"resume: checkpoint value of {k!r} has shape {a.shape}, expected {raw[k].shape}"
            )
        new_raw[k] = jnp.asarray(a, raw[k].dtype)
    opt_state = unpack_tree(ck["opt_state"], opt_state)
    tr.restore(ck)
    return new_raw, opt_state
