"""``planetref adjust NETWORK.toml --out DIR``: bundle-adjust an existing control network.

The configuration is layered: defaults, then the network file's ``[adjustment]`` table,
then ``--config FILE`` (TOML or JSON with the same structure), then the shorthand options
(``--solve``, ``--loss``, ``--sigma-px``, ``--no-outliers``, ``--rpc-bias``...), then
``--set KEY=VALUE`` overrides (dotted keys, TOML values:
``--set 'csm.pointing_offset.sigma_rad="2 mrad"'``). The resolved configuration is
written next to the outputs (config.json, config.toml).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

import click

from planetref.errors import InputError
from planetref.runtime.settings import deep_merge

__all__ = ["adjust_command"]

#: ``--solve`` names -> configuration blocks (CSM images and native strips).
SOLVE_BLOCKS: dict[str, tuple[str, str]] = {
    "position": ("csm", "position_offset"),
    "position-rate": ("csm", "position_rate"),
    "pointing": ("csm", "pointing_offset"),
    "pointing-rate": ("csm", "pointing_rate"),
    "pointing-acceleration": ("csm", "pointing_acceleration"),
    "focal-length": ("csm", "focal_length"),
    "node-position": ("linescan", "position"),
    "node-attitude": ("linescan", "attitude"),
    "interior": ("linescan", "interior"),
}


def _load_config_file(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot read the configuration ({exc})", path=path) from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"malformed configuration ({exc})", path=path) from None
    except RecursionError:
        raise InputError("the configuration is nested too deeply", path=path) from None
    if not isinstance(data, dict):
        raise InputError("the configuration must be a table", path=path)
    for table in ("adjustment", "adjust"):  # the network file's table, georef's table
        if isinstance(data.get(table), dict):
            return data[table]
    return data


def _validated(cfg: dict[str, Any], source: Path | None, what: str) -> None:
    """Check the configuration as layered so far, naming where the layer came from."""
    from planetref.adjust.config import AdjustConfig
    from planetref.runtime.settings import validate_settings

    validate_settings(AdjustConfig, cfg, source=None if source is None else str(source), what=what)


def _set(cfg: dict[str, Any], assignment: str) -> None:
    if "=" not in assignment:
        raise InputError(f"--set expects KEY=VALUE, got {assignment!r}")
    key, raw = assignment.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise InputError(f"--set has an empty key: {assignment!r}")
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()
    node = cfg
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise InputError(f"--set {key}: {p!r} is not a table")
    node[parts[-1]] = value


def _apply_solve(cfg: dict[str, Any], names: str) -> None:
    """Solve the named terms; fix the other terms of the same camera family."""
    chosen = [n.strip() for n in names.split(",") if n.strip()]
    unknown = sorted(set(chosen) - set(SOLVE_BLOCKS))
    if unknown or not chosen:
        raise InputError(
            f"--solve: unknown or no term(s) {unknown}; choose from {sorted(SOLVE_BLOCKS)}"
        )
    from planetref.adjust.config import AdjustConfig

    current = deep_merge(AdjustConfig().model_dump(), cfg)
    families = {SOLVE_BLOCKS[n][0] for n in chosen}
    for name, (section, block) in SOLVE_BLOCKS.items():
        if section not in families:
            continue
        # The whole block, so that its configured (or default) sigmas stay with it.
        blk = dict(current[section][block])
        cfg.setdefault(section, {})
        if name in chosen:
            # Weighted when the block has an a-priori sigma, free otherwise.
            has_sigma = any(
                k.startswith("sigma") and v is not None for k, v in current[section][block].items()
            )
            blk["mode"] = "weighted" if has_sigma else "free"
        else:
            blk["mode"] = "fixed"
        cfg[section][block] = blk


def _toml_safe(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _toml_safe(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list | tuple):
        return [_toml_safe(v) for v in obj]
    return obj


@click.command("adjust")
@click.argument("network", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output run folder (new, empty, or a previous adjust's with --overwrite).",
)
@click.option(
    "--overwrite",
    is_flag=True,
    help="Replace a previous adjust's outputs in --out (only its files; never other files).",
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Configuration file (TOML or JSON), over the network's: the keys of its "
    "[adjustment] table, at the top level or inside [adjustment] or [adjust].",
)
@click.option(
    "--solve",
    default=None,
    metavar="TERMS",
    help="Comma-separated terms to solve, others fixed: CSM images: position, "
    "position-rate, pointing, pointing-rate, pointing-acceleration, "
    "focal-length; native strips: node-position, node-attitude, interior.",
)
@click.option(
    "--loss",
    type=click.Choice(["linear", "huber", "cauchy"]),
    default=None,
    help="Robust loss of the first round.",
)
@click.option(
    "--sigma-px", type=float, default=None, help="Sigma of measures without their own (pixels)."
)
@click.option("--no-outliers", is_flag=True, help="Do not apply the 3 x RMSE rule.")
@click.option(
    "--tie-sigma",
    default=None,
    metavar="SIGMA|free",
    help="A-priori sigma of tie points without their own (metres or e.g. '0.5 km'; "
    "default 200 m); 'free' leaves them free (the datum may float).",
)
@click.option("--no-vce", is_flag=True, help="Keep the a-priori sigmas (no variance components).")
@click.option("--max-iterations", type=int, default=None, help="LM iterations per round.")
@click.option(
    "--set",
    "assignments",
    multiple=True,
    metavar="KEY=VALUE",
    help="Override a configuration entry (dotted key, TOML value); repeatable.",
)
@click.option(
    "--rpc-bias",
    type=click.Choice(["shift", "shift+drift", "affine"]),
    default=None,
    help="Bias model of RPC images (image-space, per image; default affine).",
)
@click.option(
    "--no-rpc",
    is_flag=True,
    help="Do not refit RPCs to adjusted rigorous cameras (RPC images always get their "
    "refined RPC).",
)
@click.option("--no-plots", is_flag=True, help="Do not draw residual plots.")
@click.pass_context
def adjust_command(
    ctx: click.Context,
    network: Path,
    out_dir: Path,
    overwrite: bool,
    config_file: Path | None,
    solve: str | None,
    loss: str | None,
    sigma_px: float | None,
    no_outliers: bool,
    tie_sigma: str | None,
    no_vce: bool,
    max_iterations: int | None,
    assignments: tuple[str, ...],
    rpc_bias: str | None,
    no_rpc: bool,
    no_plots: bool,
) -> None:
    """Bundle-adjust the control network NETWORK.toml and write the results to --out.

    Prints the headline numbers as JSON (the 'adjustment' block of report.json).
    """
    from planetref.adjust.network_file import read_network
    from planetref.pipeline.rundir import RunDir, config_digest
    from planetref.runtime.tomlfile import read_toml

    quiet = bool(ctx.obj.get("quiet")) if ctx.obj else False
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out exists and is not a folder", path=out_dir)
    doc = read_toml(network, "network file")
    cfg: dict[str, Any] = (
        dict(doc.get("adjustment", {})) if isinstance(doc.get("adjustment"), dict) else {}
    )
    _validated(cfg, network, "adjustment configuration ([adjustment] table)")
    if config_file is not None:
        cfg = deep_merge(cfg, _load_config_file(config_file))
        _validated(cfg, config_file, "adjustment configuration")
    if solve is not None:
        _apply_solve(cfg, solve)
    if loss is not None:
        cfg.setdefault("solver", {})["loss"] = loss
    if sigma_px is not None:
        cfg.setdefault("observations", {})["sigma_px"] = sigma_px
    if no_outliers:
        cfg.setdefault("outliers", {})["enabled"] = False
    if tie_sigma is not None:
        value: Any = None if tie_sigma.strip().lower() == "free" else tie_sigma.strip()
        try:
            value = float(value) if value is not None else None
        except ValueError:
            pass  # a string with a unit, validated by the configuration
        cfg.setdefault("observations", {})["tie_apriori_sigma_m"] = value
    if no_vce:
        cfg.setdefault("variance", {})["enabled"] = False
    if max_iterations is not None:
        cfg.setdefault("solver", {})["max_iterations"] = max_iterations
    if rpc_bias is not None:
        cfg.setdefault("rpc", {})["bias"] = rpc_bias
    _validated(cfg, None, "option value (--solve, --loss, --sigma-px, --tie-sigma, ...)")
    for a in assignments:
        _set(cfg, a)
    if assignments:
        _validated(cfg, None, "adjustment configuration (after --set)")
    nf = read_network(network, config=cfg)
    resolved = nf.config.model_dump(mode="json")
    # The inputs are read and checked before the folder is claimed (nothing is left
    # behind by a bad network); --overwrite replaces only the files a previous adjust wrote.
    run = RunDir(
        out_dir,
        "adjust",
        {"network": str(network.resolve()), "config": config_digest(resolved)},
        overwrite=overwrite,
        inputs=[network, nf.measures_path, *nf.camera_files.values()],
        resumable=False,
    )
    with run.logging_to_file():
        _adjust_into(
            run.path, nf, resolved, network, quiet=quiet, rpc=not no_rpc, plots=not no_plots
        )


def _adjust_into(
    out_dir: Path,
    nf: Any,
    resolved: dict[str, Any],
    network: Path,
    *,
    quiet: bool,
    rpc: bool,
    plots: bool,
) -> None:
    import tomli_w

    from planetref.adjust.api import adjust
    from planetref.report.adjustment import write_outputs
    from planetref.runtime.atomic import write_text_atomic

    def progress(msg: str) -> None:
        if not quiet:
            click.echo(msg, err=True)

    result = adjust(nf.network, nf.config, progress=progress)
    write_text_atomic(out_dir / "config.toml", tomli_w.dumps({"adjustment": _toml_safe(resolved)}))
    write_outputs(
        result,
        out_dir,
        rpc=rpc,
        plots=plots,
        extra={
            "inputs": {
                "network": str(network.resolve()),
                "measures": str(nf.measures_path),
                "convention": nf.convention,
                "cameras": {k: str(v) for k, v in nf.camera_files.items()},
            }
        },
    )
    click.echo(json.dumps({k: v for k, v in result.summary().items()}, indent=1))
