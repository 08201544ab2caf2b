"""Test set-up: float64 by default, rank promotion raises (catches silent broadcasting)."""

import os

import jax
import pytest

os.environ["DIFFCLOTH_CACHE"] = "off"  # CLI calls in tests leave the user's compilation cache alone
# XLA's small-loop option (diffcloth.runtime.tune_xla_cpu) speeds up runs but lengthens float64
# compiles by about a fifth, and this suite is compile-bound: off here unless asked for
# (`DIFFCLOTH_XLA_TUNING=on pytest`; the whole suite passes with it on). test_runtime checks, in
# fresh processes, that `import diffcloth` sets it and that XLA then compiles small loops as one.
os.environ.setdefault("DIFFCLOTH_XLA_TUNING", "off")

# One JAX compilation cache per test run, shared by the xdist workers (the controller makes the
# folder; workers inherit the variable) and removed at the end: tests that build the same program
# through their own jit wrappers, or on the other worker, load it instead of compiling again.
# Nothing outlives the run, so every run compiles from scratch.
if "DIFFCLOTH_TEST_JAX_CACHE" not in os.environ:
    import atexit
    import shutil
    import tempfile

    _cache = tempfile.mkdtemp(prefix="diffcloth-test-jax-cache-")
    os.environ["DIFFCLOTH_TEST_JAX_CACHE"] = _cache
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", os.environ["DIFFCLOTH_TEST_JAX_CACHE"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_configure(config):
    """LLVM -O0 for a run that leaves the slow tests out (the default `-m 'not slow'`).

    That run is compile-bound, and most of a CPU compile is LLVM optimizing code that then runs
    for milliseconds: -O0 cuts its CPU time by about a quarter (16 vs 21 min; test_robustness's
    frame gradient compiles in 11 s instead of 18 s), while compiled code runs up to 10x slower.
    It changes no IEEE semantics (XLA's CPU backend does not use fast-math). Runs that select
    slow tests (long rollouts and fits, bound by run time) keep XLA's default level, as do
    users' programs, every benchmark and test_runtime's fresh processes. Opt out:
    DIFFCLOTH_TEST_XLA_OPT=default, or name the option in XLA_FLAGS. Runs before any JAX
    backend starts (XLA reads XLA_FLAGS once); xdist workers inherit it and run this again."""
    markexpr = config.getoption("markexpr", "") or ""
    if markexpr.strip() != "not slow" or os.environ.get("DIFFCLOTH_TEST_XLA_OPT") == "default":
        return
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_optimization_level=0".strip()


# ----------------------------------------------------------------------------- xdist scheduling
# pytest-xdist's work stealing hands each worker half of the collection, and an idle worker then
# steals the back half of the other's queue, cutting wherever that falls: often inside a test
# file, whose tests then compile the file's shared jitted programs (e.g. test_robustness's frame
# and its gradient, ~50 s) on both workers at once. This scheduler cuts at the nearest file
# boundary instead, and splits a file only when nothing else is left to share and at least
# WHOLE_FILE_TESTS of its tests are pending (a shorter tail stays with its worker: the other
# would compile the same programs again, costing more than it waits).
WHOLE_FILE_TESTS = 16


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") != "worksteal":
        return None
    try:  # pytest-xdist internals (3.x); without them, xdist's own work stealing runs
        from xdist.scheduler.worksteal import MIN_PENDING, WorkStealingScheduling
    except ImportError:
        return None

    class FileAwareWorkStealing(WorkStealingScheduling):
        def _file(self, i):
            return self.collection[i].split("::")[0]

        def _boundary(self, items, k):
            """The file boundary in `items` nearest to position k (0 < result < len), else k."""
            n = len(items)
            for d in range(n):
                for j in (k + d, k - d):
                    if 0 < j < n and self._file(items[j - 1]) != self._file(items[j]):
                        return j
            return k

        def _send_tests(self, node, num):
            if 0 < num < len(self.pending):
                num = self._boundary(self.pending, num)
            super()._send_tests(node, num)

        def check_schedule(self):
            # WorkStealingScheduling.check_schedule with the steal cut at a file boundary
            nodes = [(n, p) for n, p in self.node2pending.items() if not n.shutting_down]
            idle = [n for n, p in nodes if len(p) < MIN_PENDING]
            if not idle:
                return
            if self.pending:
                for i, node in enumerate(idle):
                    self._send_tests(node, len(self.pending) // (len(idle) - i))
                if all(len(p) >= MIN_PENDING for n, p in nodes):
                    return
                idle = [n for n, p in nodes if len(p) < MIN_PENDING]
            if self.steal_requested_from_node is not None or not nodes:
                return
            node, pending = max(nodes, key=lambda np_: len(np_[1]))
            num = min(len(pending) // 2, max(0, len(pending) - MIN_PENDING))
            if num == 0:
                for n in idle:
                    n.shutdown()  # nothing left to steal: run the last test now
                return
            start = self._boundary(pending, len(pending) - num)
            one_file = self._file(pending[0]) == self._file(pending[-1])
            if one_file and len(pending) < WHOLE_FILE_TESTS:
                # the last few tests of one file: their shared programs (compiled, or being
                # compiled, by the worker that holds them) would be compiled again on the idle
                # one, costing more than the wait
                for n in idle:
                    n.shutdown()
                return
            if not MIN_PENDING <= start < len(pending):
                start = len(pending) - num
            node.send_steal(pending[start:])
            self.steal_requested_from_node = node

    return FileAwareWorkStealing(config, log)
