"""Matcher calls of the front end: one tile at a time, or the stages of several tiles batched.

A tile's matching (:func:`planetref.frontend.tile.tile_steps`) is a generator: it yields a
:class:`StageRequest` for each stage's matcher call (coarse, fine, a second fine pass) and
takes back a :class:`StageAnswer`. :func:`run_steps` answers them one pair at a time
(:meth:`Matcher.match`, what :func:`~planetref.frontend.tile.match_tile` does);
:func:`run_batched` advances several tiles together and answers the requests of one round
with one :meth:`~planetref.matching.base.BaseMatcher.match_many` call per matcher, so the
learned sparse matchers run their detectors on batches of images (``[frontend]
batch_tiles``). Everything but the matcher call stays per tile, in the same order, so the
results equal tile-by-tile matching to the matchers' batched tolerance (keypoints 1e-3 px,
confidences 2e-3; exactly for matchers that do not batch).
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from planetref.frontend.result import TileResult
from planetref.matching.base import Matcher, Matches

__all__ = [
    "StageAnswer",
    "StageRequest",
    "TileSteps",
    "answer",
    "inference_mode",
    "run_batched",
    "run_steps",
]


def inference_mode() -> contextlib.AbstractContextManager[Any]:
    """``torch.inference_mode()`` when torch is loaded already, else a null context."""
    # Only when the matcher already brought torch in: importing it here would cost
    # seconds for matchers that do not need it.
    torch = sys.modules.get("torch")
    if torch is not None:
        return torch.inference_mode()
    return contextlib.nullcontext()


@dataclass(frozen=True)
class StageRequest:
    """One stage's matcher call, asked of its driver by a tile's steps.

    Attributes:
        matcher: The matcher of the stage.
        image: The CCD side of the stage (the tile on the stage's grid).
        valid: Its valid pixels.
        ref_image: The reference window of the stage.
        ref_valid: Its valid pixels.
    """

    matcher: Matcher
    image: NDArray[np.float32]
    valid: NDArray[np.bool_]
    ref_image: NDArray[np.float32]
    ref_valid: NDArray[np.bool_]

    def pair(self) -> tuple[Any, Any, Any, Any]:
        """``(image0, image1, mask0, mask1)`` as :meth:`Matcher.match` takes them."""
        return (self.image, self.ref_image, self.valid, self.ref_valid)


class StageAnswer(NamedTuple):
    """What the driver sends back for a :class:`StageRequest`.

    Attributes:
        matches: The matcher's result.
        seconds: Wall seconds of the call (a batch's seconds shared equally by its pairs).
        forward: Seconds of the model call itself (``Matcher.timings["forward"]``; shared
            likewise).
    """

    matches: Matches
    seconds: float
    forward: float


TileSteps = Generator[StageRequest, StageAnswer, TileResult]
"""A tile's matching: yields each stage's matcher call, returns the tile's result."""


def _forward(matcher: Matcher, elapsed: float) -> float:
    timings = getattr(matcher, "timings", {}) or {}
    return float(timings.get("forward", elapsed))


def answer(request: StageRequest) -> StageAnswer:
    """Make one stage's matcher call (one pair, :meth:`Matcher.match`)."""
    t0 = time.perf_counter()
    with inference_mode():
        m = request.matcher.match(*request.pair())
    elapsed = time.perf_counter() - t0
    return StageAnswer(m, elapsed, _forward(request.matcher, elapsed))


def run_steps(steps: TileSteps) -> TileResult:
    """Drive one tile's steps, one matcher call at a time; the tile's result."""
    try:
        request = next(steps)
        while True:
            request = steps.send(answer(request))
    except StopIteration as stop:
        return stop.value


def _answers(requests: Sequence[StageRequest], batch_size: int) -> list[StageAnswer]:
    """One ``match_many`` call for requests of one matcher (``batch_size`` tiles a batch)."""
    matcher = requests[0].matcher
    many = getattr(matcher, "match_many", None)
    if many is None or len(requests) == 1:
        return [answer(r) for r in requests]
    t0 = time.perf_counter()
    with inference_mode():
        # two images per tile (CCD side and reference window) go through the detector
        got = many([r.pair() for r in requests], batch_size=2 * batch_size)
    elapsed = time.perf_counter() - t0
    share, fwd = elapsed / len(requests), _forward(matcher, elapsed) / len(requests)
    return [StageAnswer(m, share, fwd) for m in got]


def run_batched(steps: Sequence[TileSteps], batch_size: int) -> list[TileResult | BaseException]:
    """Drive several tiles' steps together, batching each round's matcher calls.

    Every round collects the pending request of each unfinished tile and answers those of
    one matcher with one ``match_many`` call (tiles at the coarse stage and at the fine
    stage may share a round; images of one shape share a forward pass). Should a batched
    call fail, its requests are made again one at a time, so that only the tile whose
    pair fails gets the exception.

    Args:
        steps: One generator per tile (:func:`planetref.frontend.tile.tile_steps`).
        batch_size: Tiles per forward pass (``[frontend] batch_tiles``).

    Returns:
        Per tile, in order: its result, or the exception its steps raised.
    """
    out: list[TileResult | BaseException | None] = [None] * len(steps)
    pending: dict[int, StageRequest] = {}

    def advance(i: int, step: Callable[[], StageRequest]) -> None:
        try:
            pending[i] = step()
        except StopIteration as stop:
            pending.pop(i, None)
            out[i] = stop.value
        except Exception as exc:  # the tile's own failure: the caller decides
            pending.pop(i, None)
            out[i] = exc

    for i, g in enumerate(steps):
        advance(i, g.__next__)
    while pending:
        groups: dict[int, list[int]] = {}
        for i, r in pending.items():
            groups.setdefault(id(r.matcher), []).append(i)
        for members in groups.values():
            requests = [pending[i] for i in members]
            try:
                answers = _answers(requests, batch_size)
            except Exception:
                for i, r in zip(members, requests, strict=True):
                    try:
                        got = answer(r)
                    except Exception as exc:
                        advance(i, lambda i=i, exc=exc: steps[i].throw(exc))
                    else:
                        advance(i, lambda i=i, got=got: steps[i].send(got))
                continue
            for i, got in zip(members, answers, strict=True):
                advance(i, lambda i=i, got=got: steps[i].send(got))
    return out  # type: ignore[return-value]  # every entry is set once its steps end
