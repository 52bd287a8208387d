"""Matching every tile of a strip: tile plans, the journal, and in-process or parallel dispatch.

:func:`match_strip` plans the tiles of each CCD (:mod:`~planetref.frontend.tiles`),
resumes from the journal (:mod:`~planetref.frontend.journal`), and matches the pending
tiles here or on a parallel executor (:mod:`planetref.runtime.execute`) through the tile tasks of
:mod:`~planetref.frontend.tasks`. Results are journalled as they arrive and returned in
plan order whatever the executor.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from os import PathLike

from planetref.camera.base import Camera, Terrain
from planetref.errors import InputError
from planetref.frontend.batched import TileSteps, run_batched, run_steps
from planetref.frontend.config import FrontendConfig
from planetref.frontend.journal import DEFAULT_MAX_ATTEMPTS, TileJournal, journal_digest
from planetref.frontend.result import StripMatches, TileResult, error_result
from planetref.frontend.tasks import MatcherRecipe, TileSources, TileTask, run_tile_task
from planetref.frontend.tile import TileInputs, tile_steps
from planetref.frontend.tiles import Tile, TilePlan, plan_tiles
from planetref.matching.base import Matcher
from planetref.raster.image import CcdImage
from planetref.raster.ortho import ReferenceOrtho
from planetref.runtime.execute import Executor

__all__ = ["match_strip"]

_log = logging.getLogger(__name__)

MatcherLike = Matcher | MatcherRecipe


def _name(m: MatcherLike) -> str:
    return str(getattr(m, "name", type(m).__name__))


def match_strip(
    camera: Camera,
    images: Mapping[str, CcdImage | str | PathLike[str]],
    ref: ReferenceOrtho | str | PathLike[str],
    terrain: Terrain | str | PathLike[str],
    matcher: MatcherLike,
    config: FrontendConfig | None = None,
    *,
    ccds: Sequence[str] | None = None,
    journal: str | PathLike[str] | None = None,
    max_attempts: int = DEFAULT_MAX_ATTEMPTS,
    progress: bool = True,
    raise_errors: bool = False,
    debug_tiles: Sequence[str] = (),
    debug_sink: Callable[[TileResult], None] | None = None,
    panels_dir: str | PathLike[str] | None = None,
    coarse_matcher: MatcherLike | None = None,
    executor: Executor | None = None,
    sources: TileSources | None = None,
) -> StripMatches:
    """Match every tile of every CCD image of a strip against the reference.

    Rasters are only read through windows (one tile at a time), so memory stays bounded
    by the tile size whatever the image size.

    Args:
        camera: The initial camera of the strip (all CCDs).
        images: CCD name -> image reader or path.
        ref: The reference orthoimage (reader or path).
        terrain: The reference DEM (a terrain, or a GeoTIFF path read as
            :class:`~planetref.raster.dem.GridTerrain`).
        matcher: The fine-stage matcher: an instance, or a
            :class:`~planetref.frontend.tasks.MatcherRecipe` (built here when a tile is
            matched in this process; the only form a parallel executor accepts).
        config: Front-end settings.
        ccds: CCDs to match (default: every CCD of ``images`` that the camera knows, in
            the camera's order).
        journal: A JSON-lines file: tiles already in it are not matched again (resume),
            except tiles that errored, which are tried again up to ``max_attempts``
            times in all; each new result is appended (fsynced) when done.
        max_attempts: Attempts of a tile that errors, over all resumed runs.
        progress: Show a tqdm progress bar.
        raise_errors: Re-raise exceptions of a tile instead of recording status ``error``.
        debug_tiles: Tile ids whose stage images are kept (``result.debug``).
        debug_sink: Called with every tile result matched in this process, its stage
            images attached (``result.debug``), before it is recorded; the stage images
            are dropped afterwards (except for ``debug_tiles``), so memory stays bounded.
            Figures keep what they need from the matching pass instead of matching again.
        panels_dir: With a parallel ``executor`` and ``debug_sink``: the folder where the
            workers write the stage images of the tiles they match
            (:func:`planetref.frontend.tile_panels.save_panels`, a
            :class:`~planetref.frontend.tile_panels.PanelStore`'s folder); each such result
            then goes to ``debug_sink`` too, without stage images, before it is recorded.
        coarse_matcher: Matcher of the coarse stage (default: ``matcher``).
        executor: A :class:`planetref.runtime.execute.Executor` for the tiles (default: in this
            process, one after another). A parallel one sends each worker a
            :class:`~planetref.frontend.tasks.TileTask`; ``debug_tiles`` are matched here.
        sources: The strip's file paths; required by a parallel ``executor``.

    Returns:
        The strip's tile results.

    Raises:
        InputError: Unknown CCD names, a journal of another matcher/config, or a parallel
            executor without ``sources`` or with matcher instances.
    """
    from tqdm.auto import tqdm

    cfg = config or FrontendConfig()
    name = _name(matcher)
    known = tuple(camera.ccd_names)
    unknown = sorted(set(images) - set(known))
    if unknown:
        raise InputError(f"images given for unknown CCDs {unknown}; the camera has {list(known)}")
    todo_ccds = [c for c in known if c in images] if ccds is None else list(ccds)
    missing = [c for c in todo_ccds if c not in images]
    if missing:
        raise InputError(f"no image for CCDs {missing}")
    parallel = executor is not None and executor.parallel
    if parallel:
        _check_parallel(executor, sources, matcher, coarse_matcher, todo_ccds)
        if cfg.batch_tiles > 1:
            _log.warning(
                "[frontend] batch_tiles = %d applies to tiles matched in this process; the "
                "%s workers match one tile at a time",
                cfg.batch_tiles,
                executor.name,  # type: ignore[union-attr]  # parallel: an executor
            )

    opened: list[ReferenceOrtho | CcdImage] = []
    try:
        if not isinstance(ref, ReferenceOrtho):
            ref = ReferenceOrtho(ref)
            opened.append(ref)
        if isinstance(terrain, str | PathLike):
            from planetref.raster.dem import GridTerrain

            terrain = GridTerrain.from_geotiff(terrain)
        readers: dict[str, CcdImage] = {}
        for c in todo_ccds:
            src = images[c]
            if isinstance(src, CcdImage):
                readers[c] = src
            else:
                readers[c] = CcdImage(src)
                opened.append(readers[c])
            if readers[c].shape != tuple(camera.image_size(c)):
                raise InputError(
                    f"CCD {c!r}: image is {readers[c].shape} (lines, samples) "
                    f"but the camera says {tuple(camera.image_size(c))}"
                )

        plans = {c: plan_tiles(camera, c, ref, terrain, cfg) for c in todo_ccds}
        all_tiles = [t for c in todo_ccds for t in plans[c].tiles]
        built: dict[str, Matcher] = {}

        def instance(which: str, m: MatcherLike) -> Matcher:
            if isinstance(m, MatcherRecipe):
                if which not in built:
                    built[which] = m.build()
                return built[which]
            return m

        def kept(t: Tile, r: TileResult) -> TileResult:
            if debug_sink is not None and r.debug:
                debug_sink(r)
                if t.tile_id not in debug_tiles:
                    r.debug = []
            return r

        def steps(t: Tile) -> TileSteps:
            return tile_steps(
                t,
                TileInputs(
                    image=readers[t.ccd],
                    camera=camera,
                    ref=ref,
                    terrain=terrain,
                    matcher=instance("fine", matcher),
                    config=cfg,
                    ratio=plans[t.ccd].ratio,
                    debug=debug_sink is not None or t.tile_id in debug_tiles,
                    coarse_matcher=None
                    if coarse_matcher is None
                    else instance("coarse", coarse_matcher),
                ),
            )

        def failed(t: Tile, exc: BaseException) -> TileResult:
            if raise_errors or not isinstance(exc, Exception):
                raise exc
            return error_result(t, name, cfg.geometry, exc)

        def match_here(t: Tile) -> TileResult:
            try:
                return kept(t, run_steps(steps(t)))
            except Exception as exc:
                return failed(t, exc)

        def match_batch(batch: Sequence[Tile]) -> list[TileResult]:
            got = run_batched([steps(t) for t in batch], cfg.batch_tiles)
            return [
                failed(t, r) if isinstance(r, BaseException) else kept(t, r)
                for t, r in zip(batch, got, strict=True)
            ]

        jr = (
            None
            if journal is None
            else TileJournal(
                journal, journal_digest(name, cfg.identity()), max_attempts=max_attempts
            )
        )
        results: dict[str, TileResult] = {}
        if jr is not None:
            done = jr.open()
            results.update({t.tile_id: done[t.tile_id] for t in all_tiles if t.tile_id in done})
        pending = [t for t in all_tiles if t.tile_id not in results]

        def record(r: TileResult) -> None:
            results[r.tile_id] = r
            if jr is not None:
                jr.append(r)

        try:
            if parallel:
                _match_parallel(
                    executor,  # type: ignore[arg-type]
                    _Dispatch(sources, matcher, coarse_matcher, cfg, plans, raise_errors),  # type: ignore[arg-type]
                    pending,
                    match_here,
                    record,
                    None if debug_sink is None or panels_dir is None else str(panels_dir),
                    debug_sink,
                    progress,
                    set(debug_tiles),
                )
            else:
                bar = tqdm(
                    total=len(pending),
                    desc=f"matching ({name})",
                    unit="tile",
                    disable=None if progress else True,
                )
                n = cfg.batch_tiles
                for a in range(0, len(pending), n):
                    batch = pending[a : a + n]
                    for r in [match_here(batch[0])] if n == 1 else match_batch(batch):
                        record(r)
                        bar.update(1)
                    bar.set_postfix(ok=sum(x.status == "ok" for x in results.values()))
                bar.close()
        finally:
            if jr is not None:
                jr.close()
        return StripMatches(name, cfg, plans, [results[t.tile_id] for t in all_tiles])
    finally:
        for obj in opened:
            obj.close()


def _check_parallel(
    executor: Executor,
    sources: TileSources | None,
    matcher: MatcherLike,
    coarse: MatcherLike | None,
    ccds: Sequence[str],
) -> None:
    if not isinstance(sources, TileSources):
        raise InputError(
            f"the {executor.name} executor needs sources= (a TileSources with "
            "the camera, image, reference and DEM paths)"
        )
    for m in (matcher, coarse):
        if m is not None and not isinstance(m, MatcherRecipe):
            raise InputError(
                f"the {executor.name} executor builds the matchers in its workers: pass "
                f"them as MatcherRecipe (name and options), not as an instance of {_name(m)!r}"
            )
    lacking = sorted(set(ccds) - {c for c, _ in sources.images})
    if lacking:
        raise InputError(f"sources= has no image path for CCDs {lacking}")


class _Dispatch:
    """What every tile task of a strip shares."""

    def __init__(
        self,
        sources: TileSources,
        fine: MatcherRecipe,
        coarse: MatcherRecipe | None,
        cfg: FrontendConfig,
        plans: Mapping[str, TilePlan],
        raise_errors: bool,
    ) -> None:
        self.key = sources.key()
        self.fine, self.coarse, self.cfg = fine, coarse, cfg
        self.plans, self.raise_errors = plans, raise_errors

    def task(self, t: Tile, panels: str | None = None) -> TileTask:
        return TileTask(
            self.key,
            self.fine,
            self.coarse,
            t,
            self.cfg,
            self.plans[t.ccd].ratio,
            self.raise_errors,
            panels,
        )


def _match_parallel(
    executor: Executor,
    dispatch: _Dispatch,
    pending: list[Tile],
    match_here: Callable[[Tile], TileResult],
    record: Callable[[TileResult], None],
    panels: str | None,
    sink: Callable[[TileResult], None] | None,
    progress: bool,
    debug: set[str],
) -> None:
    """The pending tiles on a parallel executor, each recorded (journalled) as it arrives.

    ``debug`` tiles are matched here with ``match_here`` (their stage images do not travel).
    With ``panels`` the workers write every tile's stage images into that folder, and
    each arriving result goes to ``sink`` first.
    """
    from tqdm.auto import tqdm

    remote = [t for t in pending if t.tile_id not in debug]
    name = dispatch.fine.name
    bar = tqdm(
        total=len(pending),
        desc=f"matching ({name}, {executor.name})",
        unit="tile",
        disable=None if progress else True,
    )
    n_ok = 0
    try:
        for t in pending:
            if t.tile_id in debug:
                record(match_here(t))
                bar.update(1)
        tasks = [dispatch.task(t, panels) for t in remote]
        for out in executor.map_unordered(run_tile_task, tasks):
            t = remote[out.index]
            if out.error is not None:
                if dispatch.raise_errors:
                    raise out.error
                r = error_result(t, name, dispatch.cfg.geometry, out.error)
            else:
                r = TileResult.from_dict(out.result)
                if panels is not None and sink is not None:
                    sink(r)
            record(r)
            n_ok += r.status == "ok"
            bar.update(1)
            bar.set_postfix(ok=n_ok)
    finally:
        bar.close()
