"""Reverse mode through the wear loops: what their checkpointed scans keep.

Both loops (eq 23's updates, the adaptive integrator's attempts) scan in two levels, an
outer scan of `jax.checkpoint`ed blocks of √n inner steps, each step checkpointed too, so
that reverse-mode memory grows like √n and not like n × steps × nodes. A checkpointed step
is run again in the backward pass, and most of a step's time is the contact solve's Newton
iterations (~80 % of a cycle at 360 x 360, docs/performance.md). Their answers carry no
derivative (the implicit-function correction after them does: `contact`), so they are kept
instead (`jax.ad_checkpoint.checkpoint_name`, `NEWTON`): per contact solve 7 numbers a
step (the offset, the residual, the 2 x 2 Hessian), 20 kB at 360 steps. The inner steps
keep them always (√n of them at a time); the outer blocks keep them for all n steps where
that stays under `OUTER_BYTES`, else they run the Newton iterations again once (as before)
and keep only the block's carries.

Measured (2026-11-30, docs/performance.md, "Reverse mode keeps the Newton answers"): the
gradient of a 5-experiment rig loss at 360 x 360, M = 500 (20 updates), took 5.0x its
forward run's time before and 2.9x after.

The adaptive integrator's attempts are four Runge-Kutta stages, each a cycle: its inner
level checkpoints each *stage* (`KEEP_NEWTON`), not each attempt. A checkpointed attempt
ran again in the backward pass stacked its stages' (steps, nodes) fields (the pressure,
the rate, the contact's intermediate fields: seven at 360 x 360, 1 MB each), and writing
and reading them (dynamic-slice fusions and copies) was ~1/4 of the backward pass. A
checkpointed stage keeps its carries and Newton's answers and is run again alone. The
gradient of the rig's adaptive loss took 3.9-4.1x its forward run's time before and
2.5-2.6x after, the boom's 3.5-3.6x and 2.3-2.4x, with the same numbers bit for bit
(docs/performance.md, "Reverse mode through the adaptive loop: each stage checkpointed").
"""

from __future__ import annotations

import jax

NEWTON = "contact_newton"
"""The name of the contact solve's Newton answers, kept by the wear loops' checkpoints."""

KEEP_NEWTON = jax.checkpoint_policies.save_only_these_names(NEWTON)
"""`jax.checkpoint` policy: keep the Newton answers, recompute everything else."""

OUTER_BYTES = 256 * 2**20
"""Most memory [bytes] the outer blocks' kept Newton answers may take (all n steps')."""

FLOATS_PER_STEP = 7  # offset (2), residual (2), Hessian (3) of each step of a cycle


def outer_policy(items: int, steps_per_cycle: int, solves_per_item: int):
    """The outer blocks' `jax.checkpoint` policy for a scan of `items` (updates or attempts)
    of `solves_per_item` contact solves over `steps_per_cycle` steps each: `KEEP_NEWTON`
    where their answers fit in `OUTER_BYTES`, else None (keep nothing but the carries)."""
    size = 8 * FLOATS_PER_STEP * steps_per_cycle * solves_per_item * items
    return KEEP_NEWTON if size <= OUTER_BYTES else None
