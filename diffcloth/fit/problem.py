"""What a fit checkpoint was fitting, so that `diffcloth fit --resume` continues only the same
problem, and `--init-from` starts a new one from an earlier fit's parameters.

The record (the checkpoint sidecar's "problem" entry, written when the run's results are
committed) holds the config's values as a flat table and its SHA-256, whether the run was
`--smoke`, and one SHA-256 per target image (None for targets rendered from [truth], which the
config's hash covers). Keys that only say how long to fit or what to report ([fit] steps,
patience, lm_patience, identifiability, noise_sigma) are left out: a resume may change them.
"""

from __future__ import annotations

import hashlib
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "check_same_problem",
    "fit_inputs",
    "initial_from_checkpoint",
    "problem_record",
    "read_checkpoint",
    "stamp_checkpoint",
]

#: [fit] keys that a resumed fit may change (stopping rules and reporting only).
RESUMABLE_KEYS = ("steps", "patience", "lm_patience", "identifiability", "noise_sigma")
PROBLEM_FORMAT = 1


def _flatten(value, where: str, out: dict) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(v, f"{where}.{k}" if where else str(k), out)
    elif isinstance(value, list) and any(isinstance(v, dict) for v in value):
        for i, v in enumerate(value):
            _flatten(v, f"{where}[{i}]", out)
    else:
        out[where] = value


def _label(key: str) -> str:
    section, _, name = key.rpartition(".")
    return f"[{section}] {name}" if section else name


def _image_hashes(targets) -> list[list[str]]:
    """One SHA-256 per (camera, image) of a (cameras, T, H, W, 3) target video, in float32."""
    video = np.asarray(targets)
    return [
        [hashlib.sha256(np.ascontiguousarray(img, np.float32).tobytes()).hexdigest() for img in cam]
        for cam in video
    ]


def problem_record(config_path, targets=None, *, smoke: bool = False) -> dict[str, Any]:
    """The record of the fit problem of `config_path` with the loaded `targets` (None: rendered
    from [truth]). See the module docstring."""
    with Path(config_path).open("rb") as fh:
        data = tomllib.load(fh)
    flat: dict[str, Any] = {}
    _flatten(data, "", flat)
    for key in RESUMABLE_KEYS:
        flat.pop(f"fit.{key}", None)
    flat = json.loads(json.dumps(flat, default=str))  # TOML dates and times as text
    text = json.dumps(flat, sort_keys=True, allow_nan=True)
    images = None if targets is None else _image_hashes(targets)
    return {
        "format": PROBLEM_FORMAT,
        "config_sha256": hashlib.sha256(text.encode()).hexdigest(),
        "config": flat,
        "smoke": bool(smoke),
        "targets_sha256": None
        if images is None
        else hashlib.sha256(json.dumps(images).encode()).hexdigest(),
        "targets": images,
    }


def _short(value) -> str:
    text = json.dumps(value) if value is not _ABSENT else "(absent)"
    return text if len(text) <= 40 else text[:37] + "..."


_ABSENT = object()


def _config_changes(old: dict, new: dict) -> list[str]:
    keys = sorted(set(old) | set(new))
    return [
        f"{_label(k)} {_short(old.get(k, _ABSENT))} -> {_short(new.get(k, _ABSENT))}"
        for k in keys
        if old.get(k, _ABSENT) != new.get(k, _ABSENT)
    ]


def _target_changes(old, new) -> str | None:
    if old == new:
        return None
    if old is None or new is None:
        was, now = ("rendered from [truth]", "image files") if old is None else (
            "image files", "rendered from [truth]")  # fmt: skip
        return f"the targets were {was}, now they are {now}"
    if len(old) != len(new) or any(len(a) != len(b) for a, b in zip(old, new, strict=False)):
        shape = lambda v: f"{len(v)} camera(s) x {[len(c) for c in v]} images"  # noqa: E731
        return f"the targets were {shape(old)}, now {shape(new)}"
    parts = []
    for cam, (a, b) in enumerate(zip(old, new, strict=True)):
        changed = [i for i, (x, y) in enumerate(zip(a, b, strict=True)) if x != y]
        if changed:
            shown = ", ".join(str(i) for i in changed[:8]) + (", ..." if len(changed) > 8 else "")
            parts.append(f"camera {cam}: image(s) {shown} of {len(a)} changed")
    return "the targets changed (" + "; ".join(parts) + ")"


def check_same_problem(ck: dict, path, now: dict, config_path) -> None:
    """Raise ValueError, naming the checkpoint and what changed, unless the checkpoint `ck`
    (`load_checkpoint`) was written by a fit of the same problem `now` (`problem_record`)."""
    path = Path(path)
    hint = (
        f"to start a new fit from its parameters instead: diffcloth fit {config_path} --out "
        f"NEW_FOLDER --init-from {path}"
    )
    meta = ck.get("meta") or {}
    saved = meta.get("problem")
    if not isinstance(saved, dict) or saved.get("format") != PROBLEM_FORMAT:
        side = path.with_suffix(".json")
        why = "its sidecar is missing" if not side.exists() else "it records no config or targets"
        raise ValueError(
            f"checkpoint {str(path)!r} cannot be checked against this config ({why}: written by "
            f"an older diffcloth, or the sidecar {side.name} was removed); {hint}"
        )
    changes = []
    if saved.get("config_sha256") != now["config_sha256"]:
        diff = _config_changes(saved.get("config") or {}, now["config"])
        shown = "; ".join(diff[:6]) + (f"; and {len(diff) - 6} more" if len(diff) > 6 else "")
        changes.append(f"the config changed ({shown or 'its values'})")
    if bool(saved.get("smoke")) != now["smoke"]:
        was = "with" if saved.get("smoke") else "without"
        changes.append(f"the checkpoint's fit ran {was} --smoke")
    targets = _target_changes(saved.get("targets"), now["targets"])
    if targets:
        changes.append(targets)
    if changes:
        raise ValueError(
            f"checkpoint {str(path)!r} is of another problem: {'; '.join(changes)}. A resumed fit "
            f"must fit the same config and targets ([fit] {', '.join(RESUMABLE_KEYS)} may "
            f"change); {hint}"
        )


def read_checkpoint(path) -> dict:
    """`load_checkpoint`, with every failure a ValueError naming the file: a truncated or corrupt
    .npz or sidecar, one without parameter values, or the two out of step."""
    from diffcloth.fit.checkpoint import load_checkpoint

    path = Path(path)
    ck = load_checkpoint(path)
    side = path.with_suffix(".json")
    if "step" not in ck or not (ck.get("best") or ck.get("params")):
        raise ValueError(f"checkpoint {str(path)!r} is incomplete (no step or parameter values)")
    meta = ck.get("meta") or {}
    if "step" in meta and meta["step"] != ck["step"]:
        raise ValueError(
            f"checkpoint {str(path)!r} is at step {ck['step']} but its sidecar {str(side)!r} at "
            f"step {meta['step']}: one of them was replaced or damaged"
        )
    return ck


def stamp_checkpoint(path, record: dict) -> None:
    """Add the problem `record` to the sidecar of the checkpoint `path` (when there is one)."""
    from diffcloth.io.media import to_jsonable

    side = Path(path).with_suffix(".json")
    if not Path(path).is_file() or not side.is_file():
        return
    meta = json.loads(side.read_text())
    meta["problem"] = record
    tmp = side.with_name(side.name + ".tmp")
    tmp.write_text(json.dumps(to_jsonable(meta), indent=2) + "\n")
    tmp.replace(side)


def fit_inputs(config_path, init_from=None) -> list[tuple[str, Path]]:
    """The inputs of a fit run that its --out must not hold: the config, the files it names
    (targets, ...) and the --init-from checkpoint with its sidecar."""
    from diffcloth.outdir import config_inputs

    found = config_inputs(config_path)
    if init_from is not None:
        p = _checkpoint_file(init_from)
        found += [("--init-from checkpoint", p), ("--init-from sidecar", p.with_suffix(".json"))]
    return found


def _checkpoint_file(path) -> Path:
    p = Path(path).expanduser()
    return p / "checkpoint.npz" if p.is_dir() else p


def initial_from_checkpoint(path, settings, sc) -> tuple[Path, dict, str]:
    """(checkpoint path, [fit.initial] values, a note for the report) of `--init-from PATH` (a
    checkpoint.npz or the folder holding it): its best values for the free parameters it has;
    the others keep the config's starting values. ValueError names the file on any failure."""
    from diffcloth import pipeline

    p = _checkpoint_file(path)
    if not p.is_file():
        raise ValueError(f"--init-from: no checkpoint {str(p)!r}")
    try:
        ck = read_checkpoint(p)
    except ValueError as err:
        raise ValueError(f"--init-from: {err}") from None
    best = ck.get("best") or ck.get("params")
    names = [n for n in settings.free if n not in (settings.ties or {})]
    initial = dict(settings.initial)
    taken = []
    for n in names:
        if n not in best:
            continue
        want = np.shape(pipeline.param_value(sc, n))
        value = np.asarray(best[n])
        if value.shape != want:
            raise ValueError(
                f"--init-from {str(p)!r}: its value of {n} has shape {value.shape}, this fit's "
                f"{want}"
            )
        if not np.all(np.isfinite(value)):
            raise ValueError(f"--init-from {str(p)!r}: its value of {n} is not finite")
        initial[n] = value
        taken.append(n)
    if not taken:
        raise ValueError(
            f"--init-from {str(p)!r}: the checkpoint has values for {sorted(best)}, none of this "
            f"fit's free parameters {names}"
        )
    kept = [n for n in names if n not in taken]
    note = (
        f"A new fit started from the best parameters of the checkpoint `{p}` (--init-from): "
        + ", ".join(f"{n} = {np.asarray(initial[n]).tolist()}" for n in taken)
        + (f"; {', '.join(kept)} from the config" if kept else "")
        + "."
    )
    return p, initial, note
