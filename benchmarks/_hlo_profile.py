"""Shared by the profiling benchmarks (`fit_step_profile.py`, `render_profile.py`): XLA CPU thunk
times of a compiled program under `jax.profiler`, and the HLO tables that attribute each thunk to
the diffcloth source that most of its operations come from.
"""

from __future__ import annotations

import collections
import glob
import re
import tempfile
import time

import jax

#: profiler events that are not thunks of their own (executor, thread-pool listener, loop and
#: conditional wrappers: their bodies' thunks are counted)
SKIP = ("ThunkExecutor", "ThreadpoolListener", "while", "end:", "conditional", "cond")


def thunk_times(compiled, *args, repeats: int):
    """Run `compiled(*args)` `repeats` times under `jax.profiler` (after two untimed calls).
    Returns (ns, launches, wall): Counters of summed thunk nanoseconds and launches by thunk (HLO)
    name over all repeats, and the wall time per call in s."""
    from jax._src.profiler import ProfileData

    for _ in range(2):
        jax.block_until_ready(compiled(*args))
    with tempfile.TemporaryDirectory(prefix="diffcloth_prof_") as tmp:
        jax.profiler.start_trace(tmp)
        t = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(compiled(*args))
        wall = (time.perf_counter() - t) / repeats
        jax.profiler.stop_trace()
        data = ProfileData.from_file(glob.glob(tmp + "/**/*.xplane.pb", recursive=True)[0])
        ns, launches = collections.Counter(), collections.Counter()
        for plane in data.planes:
            for line in plane.lines:
                if not line.name.startswith("tf_XLAEigen"):
                    continue
                for ev in line.events:
                    if not ev.name.startswith(SKIP):
                        ns[ev.name] += ev.duration_ns
                        launches[ev.name] += 1
    return ns, launches, wall


def hlo_tables(text: str):
    """From a compiled program's HLO text: (instruction line by name, fused computation body by
    name, (file path, line, function) by stack frame id)."""
    files, funcs, locs, frames = {}, {}, {}, {}
    section = None
    for line in text.splitlines():
        s = line.strip()
        if s in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            section = s
            continue
        m = re.match(r"^(\d+) (.*)$", s)
        if section and m:
            i, rest = int(m.group(1)), m.group(2)
            if section == "FileNames":
                files[i] = rest.strip('"')
            elif section == "FunctionNames":
                funcs[i] = rest.strip('"')
            elif section == "FileLocations":
                get = lambda k, rest=rest: int(re.search(rf"\b{k}=(\d+)", rest).group(1))
                locs[i] = (get("file_name_id"), get("function_name_id"), get("line"))
            elif section == "StackFrames":
                frames[i] = int(re.search(r"file_location_id=(\d+)", rest).group(1))
        elif section and s:
            section = None
    where = {}
    for k, v in frames.items():
        f, fn, ln = locs[v]
        where[k] = (files.get(f, "?"), ln, funcs.get(fn, ""))
    bodies, inst, cur = {}, {}, None
    for line in text.splitlines():
        m = re.match(r"^%?([\w.-]+) .*\{$", line)
        if m and not line.startswith(" "):
            cur = m.group(1)
            bodies[cur] = []
            continue
        if cur is not None:
            bodies[cur].append(line)
        m = re.search(r"%([\w.-]+) = ", line)
        if m:
            inst[m.group(1)] = line
    return inst, bodies, where


def attribute(name, inst, bodies, key_of):
    """(key, direction, shape) of thunk `name`: the most common `key_of(stack frame id)` over
    its operations (None keys skipped; "other" if none), "backward" when any operation comes
    from a transpose (else "forward"), and its result shape."""
    line = inst.get(name, "")
    called = re.search(r"calls=%([\w.-]+)", line)
    body = bodies.get(called.group(1), []) if called else [line]
    keys = collections.Counter()
    backward = False
    for b in body:
        m = re.search(r"stack_frame_id=(\d+)", b)
        if m:
            k = key_of(int(m.group(1)))
            if k is not None:
                keys[k] += 1
        backward = backward or "transpose(" in b
    shape = re.search(r"= (\S+) ", line)
    return (
        keys.most_common(1)[0][0] if keys else "other",
        "backward" if backward else "forward",
        shape.group(1) if shape else "",
    )
