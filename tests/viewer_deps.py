"""What the viewer tests need (viser, playwright, Chromium): skip without it, or fail under
DIFFCLOTH_REQUIRE_BROWSER=1, which .ci/run sets so that CI cannot pass without them."""

from __future__ import annotations

import importlib
import os

import pytest

REQUIRE_BROWSER = os.environ.get("DIFFCLOTH_REQUIRE_BROWSER") == "1"


def skip_or_fail(reason: str):
    """pytest.skip, or pytest.fail with DIFFCLOTH_REQUIRE_BROWSER=1 (CI)."""
    if REQUIRE_BROWSER:
        pytest.fail(f"{reason} [DIFFCLOTH_REQUIRE_BROWSER=1: CI runs every viewer test]")
    pytest.skip(reason)


def need(module: str, reason: str):
    """pytest.importorskip, failing instead of skipping under DIFFCLOTH_REQUIRE_BROWSER=1."""
    try:
        return importlib.import_module(module)
    except ImportError:
        skip_or_fail(reason)
