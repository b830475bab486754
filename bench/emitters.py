"""Emitters seen directly, pasted into training items (`train.emitters`): a lamp far above the frame's exposure;
and fireflies pasted into the input only (`train.fireflies`), so that a small bright spot is not always a lamp.

The renders hold few emitters in view and none far brighter than the room they light, so the networks
never see radiance of 1e2-1e4 times a frame's exposure and, given one, return it 10-30% too bright
(results/cpu/stability, the "lamp" cases; tests/test_predict.py's lamp room). `with_emitter` pastes one
such lamp into a training item, in the input and in every target alike: a noise-free rectangle of constant
radiance (a light seen directly has no Monte Carlo noise), static over the item's frames, its gBuffer
left as the surface it covers. Its level is k times the exposure of the item's first frame without it
(`bench.exposure.frame_exposure`), log10 k uniform in LOG10_LEVEL, as the stability cases place theirs.

Lamps alone teach a network to keep any static noise-free bright block, and a cluster of Monte Carlo
fireflies looks like one: with lamps in a quarter of the items every learned model kept more of the
input's fireflies (results/cpu/studies/emitters_stability, the firefly cases; docs/studies.md). A firefly
is the other side of that line: one pixel of one frame, at the lamps' levels, in the input only (the
targets hold the converged radiance there). `with_fireflies` pastes a few per frame, each frame its own.
"""
from __future__ import annotations

import random

from bench.exposure import frame_exposure
from bench.tasks import Task

# the lamp's radiance: 10x to 3e4x the exposure of the item's first frame (the stability cases' lamps are 1e2x
# and 1e4x; tests/test_predict.py's lamp room's, radiance 3000 in a room of exposure 0.26, 1.2e4x)
LOG10_LEVEL = (1.0, 4.5)
SIDE = (2, 0.5)            # its height and width on the input's grid: 2 pixels to half the crop's side
FIREFLIES_PER_FRAME = (1, 4)   # fireflies in each frame of the input (the stability cases': 0.2% of the pixels)


def first_frame_exposure(x) -> float:
    """The exposure of an item's first frame (`bench.exposure.frame_exposure` of its (T, C, H, W) input `x`):
    what the lamps' and the fireflies' levels are multiples of."""
    return float(frame_exposure(x[:1, :3], "exposure").flatten()[0])


def with_emitter(item: dict, task: Task, draw: random.Random) -> dict:
    """`item` (buffer -> (T, C, H, W)) with a lamp pasted into task.x, task.y and task.mid where the item
    holds them (the same area: the targets' pixels cover the input's); the other buffers are the item's.
    `draw` fixes its place, size and level."""
    x = item[task.x]
    h, w = x.shape[-2:]
    rows = draw.randint(SIDE[0], max(SIDE[0], int(SIDE[1] * h)))
    cols = draw.randint(SIDE[0], max(SIDE[0], int(SIDE[1] * w)))
    top, left = draw.randint(0, max(0, h - rows)), draw.randint(0, max(0, w - cols))
    k = 10 ** draw.uniform(*LOG10_LEVEL)
    level = k * first_frame_exposure(x)
    out = dict(item)
    for name in dict.fromkeys(b for b in (task.x, task.y, task.mid) if b and b in item):
        s = item[name].shape[-1] // w   # 1 at the input's size, the task's scale at the targets'
        out[name] = item[name].clone()
        out[name][..., :3, s * top:s * (top + rows), s * left:s * (left + cols)] = level
    return out


def with_fireflies(item: dict, task: Task, draw: random.Random, exposure: float | None = None) -> dict:
    """`item` with fireflies pasted into task.x only: in each frame, its own FIREFLIES_PER_FRAME single
    pixels, each of all three channels raised to k times `exposure` (default: that of the item's first frame),
    log10 k uniform in LOG10_LEVEL (the lamps' levels: the level does not tell the two apart); a pixel
    already brighter keeps its value. `draw` fixes them all."""
    x = item[task.x]
    t, h, w = x.shape[0], *x.shape[-2:]
    if exposure is None:
        exposure = first_frame_exposure(x)
    out = dict(item)
    out[task.x] = x.clone()
    for frame in range(t):
        for _ in range(draw.randint(*FIREFLIES_PER_FRAME)):
            row, col = draw.randrange(h), draw.randrange(w)
            pixel = out[task.x][frame, :3, row, col]
            pixel.clamp_(min=10 ** draw.uniform(*LOG10_LEVEL) * exposure)
    return out
