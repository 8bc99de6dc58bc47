"""mkdocs hooks: the committed result figures and files, and Sphinx roles in docstrings.

The pages link a figure as ``../experiments/results/<run>/<name>.png`` and a results table the file
its numbers come from (``.../metrics.json``), paths that are right for the Markdown file in the
repository (``docs/<page>.md``). The hooks add every PNG and JSON file under
``experiments/results/`` to the site at ``experiments/results/...`` and rewrite those links for the
site, so the figures and results exist once, where the runs wrote them.

Docstrings name other objects as ``:func:`name```, ``:class:`Name``` and the like; Markdown shows the
role as text before the code, so the hooks drop the role and keep the code.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
RESULTS = "experiments/results/"
ROLE = re.compile(r":(?:func|class|data|meth|attr|mod|obj|exc|const):(?=<code>)")


def on_files(files, config):
    """Add the result figures and JSON files to the site's files."""
    found = [*(ROOT / RESULTS).rglob("*.png"), *(ROOT / RESULTS).rglob("*.json")]
    for path in sorted(found):
        files.append(
            File(
                path.relative_to(ROOT).as_posix(),
                src_dir=str(ROOT),
                dest_dir=config["site_dir"],
                use_directory_urls=config["use_directory_urls"],
            )
        )
    return files


def on_page_markdown(markdown, page, config, files):
    """Point the repository-relative figure links of a page at the figures added by ``on_files``."""
    depth = page.file.src_uri.count("/")
    return markdown.replace("../" * (depth + 1) + RESULTS, "../" * depth + RESULTS)


def on_page_content(html, page, config, files):
    """Drop the Sphinx role before a code span of a rendered docstring (``:func:`name``` -> ``name``)."""
    return ROLE.sub("", html)
