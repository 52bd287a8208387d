"""MkDocs hooks: the generated pages (CLI, configuration, benchmarks) added at build time.

Listed under ``hooks:`` in ``mkdocs.yml``. The pages are built in memory from the click
commands, the settings models and ``benchmarks/results/*.json`` at every build, so they
cannot drift from the code; nothing is written into ``docs/``.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mkdocs.structure.files import File, Files

_HERE = Path(__file__).resolve().parent
if str(_HERE) not in sys.path:
    sys.path.insert(0, str(_HERE))

import benchmarks_page  # noqa: E402
import cli_ref  # noqa: E402
import config_ref  # noqa: E402

GENERATED = {
    "reference/cli.md": cli_ref.page,
    "reference/configuration.md": config_ref.page,
    "benchmarks.md": benchmarks_page.page,
}


def on_files(files: Files, config) -> Files:
    """Add the generated pages to the site's files."""
    for uri, make in GENERATED.items():
        existing = files.get_file_from_path(uri)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, uri, content=make()))
    return files
