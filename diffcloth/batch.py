"""Batches of scenes or parameter guesses: `vmap` over a leading axis, spread over devices.

One batch element that diverges (NaN, inf) must not poison the others: every batched call returns
a per-element `finite` flag, and NaNs never cross elements because `vmap` keeps elements apart.

Devices: `shard_batch` places the leading axis of every leaf on a 1-D `jax.sharding.Mesh` named
"batch" with `NamedSharding(mesh, P("batch"))`; the jitted, vmapped function then runs each slice on
its own device and the result equals the unsharded one. On a CPU-only machine, test with
`XLA_FLAGS=--xla_force_host_platform_device_count=4` (set before JAX is imported). Multi-host: call
`jax.distributed.initialize()` on every host first; `jax.devices()` then lists all hosts' devices and
the same mesh spans them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

__all__ = ["batch_size", "all_finite", "make_mesh", "shard_batch", "vmap_batched"]


def batch_size(batched: Any) -> int:
    """The common leading size of every leaf of `batched`.

    Raises:
      ValueError: naming the leaves and their sizes when they disagree, or a leaf has no axis.
    """
    leaves = jax.tree_util.tree_leaves_with_path(batched)
    if not leaves:
        raise ValueError("batch is empty: it has no array leaves")
    sizes = {}
    for path, leaf in leaves:
        shape = np.shape(leaf)
        name = jax.tree_util.keystr(path) or "<root>"
        if len(shape) == 0:
            raise ValueError(
                f"batched leaf {name} is a scalar: every leaf needs a leading batch axis"
            )
        sizes[name] = shape[0]
    if len(set(sizes.values())) != 1:
        detail = ", ".join(f"{k}: {v}" for k, v in sizes.items())
        raise ValueError(f"batched leaves have mismatched leading sizes ({detail}); all must agree")
    return next(iter(sizes.values()))


def all_finite(tree: Any) -> jax.Array:
    """Per batch element: True where every leaf of that element is finite. Leaves (B, ...) -> (B,)."""
    leaves = jax.tree_util.tree_leaves(tree)
    flags = [jnp.all(jnp.isfinite(jnp.reshape(x, (x.shape[0], -1))), axis=1) for x in leaves]
    return jnp.stack(flags).all(axis=0)


def vmap_batched(fn: Callable, batched: Any, *args: Any) -> tuple[Any, jax.Array]:
    """Map `fn(element, *args)` over the leading axis of `batched`.

    Returns:
      (outputs with a leading batch axis, finite flags (B,) bool).
    """
    batch_size(batched)
    out = jax.vmap(fn, in_axes=(0,) + (None,) * len(args))(batched, *args)
    return out, all_finite(out)


def make_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh named "batch" over the first `num_devices` devices (default: all).

    Raises:
      ValueError: if more devices are asked for than exist.
    """
    devices = jax.devices()
    n = len(devices) if num_devices is None else int(num_devices)
    if not 1 <= n <= len(devices):
        raise ValueError(
            f"devices must be in [1, {len(devices)}] (the devices JAX sees), got {num_devices}; "
            "on a CPU set XLA_FLAGS=--xla_force_host_platform_device_count=N before importing jax"
        )
    return Mesh(np.array(devices[:n]), ("batch",))


def shard_batch(batched: Any, mesh: Mesh) -> Any:
    """Place every leaf's leading axis across the mesh's "batch" axis.

    Raises:
      ValueError: if the batch size is not a multiple of the number of devices.
    """
    size = batch_size(batched)
    n = mesh.devices.size
    if size % n:
        raise ValueError(f"batch size {size} must be a multiple of the number of devices {n}")
    sharding = NamedSharding(mesh, P("batch"))
    return jax.tree_util.tree_map(lambda x: jax.device_put(x, sharding), batched)
