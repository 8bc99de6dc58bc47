"""The results tables of the README and the docs against the committed results (``docs/results.py``):
the committed pages pass ``--check``, a stale copy fails naming the table and the cell, and the
script's write mode makes it pass again."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SPEC = importlib.util.spec_from_file_location("docs_results", ROOT / "docs" / "results.py")
results = importlib.util.module_from_spec(SPEC)
sys.modules[SPEC.name] = results  # its dataclasses look their module up
SPEC.loader.exec_module(results)


@pytest.fixture
def copy(tmp_path):
    """The pages copied into a repository of their own, beside the committed results."""
    for page in results.pages(ROOT):
        (tmp_path / page).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / page, tmp_path / page)
    (tmp_path / "experiments").mkdir()
    (tmp_path / results.RESULTS).symlink_to(ROOT / results.RESULTS)
    return tmp_path


def stale(root: Path, page: str, old: str, new: str) -> None:
    path = root / page
    text = path.read_text()
    assert text.count(old) == 1, f"{old!r} is not once on {page}"
    path.write_text(text.replace(old, new))


def test_the_committed_pages_match_the_committed_results():
    assert results.check(ROOT) == []


def test_a_stale_cell_fails_naming_the_table_row_and_column(copy, capsys):
    # the A stage's median of the paper's run, as the committed results give it
    median = results.q(json.loads((ROOT / results.PAPER.file).read_text())["A_error_median_nm"], "nm")
    stale(copy, "docs/positioning.md", f"| A | 64 | {median} |", "| A | 64 | 99.9 nm |")
    assert results.main(["--check", "--root", str(copy)]) == 1
    message = capsys.readouterr().err
    assert "docs/positioning.md: table 'paper_stages', row 'A', column 'median'" in message
    assert f"the page has '99.9 nm', the results give '{median}'" in message
    assert results.main(["--root", str(copy)]) == 0  # the write mode puts the results back
    assert results.check(copy) == []


def test_a_stale_readme_row_fails(copy):
    text = (copy / "README.md").read_text()
    row = next(line for line in text.split("\n") if line.startswith("| after B: < 20 nm (p95) |"))
    stale(copy, "README.md", row, row.replace("met", "**not met**", 1))
    assert any("README.md: table 'readme', row 'after B: < 20 nm (p95)'" in p for p in results.check(copy))


def test_a_table_on_no_page_and_a_marker_of_no_table_fail(copy):
    stale(copy, "docs/study.md", "<!-- results:bench_study -->", "<!-- results:bench_studies -->")
    with pytest.raises(SystemExit, match="docs/study.md: <!-- results:bench_studies --> names no table"):
        results.check(copy)
    stale(copy, "docs/study.md", "<!-- results:bench_studies -->\n", "")
    stale(
        copy,
        "docs/study.md",
        "\n<!-- /results -->\n\n<!-- results:bench_study_extras -->",
        "\n<!-- results:bench_study_extras -->",
    )
    assert "table 'bench_study' is on no page: mark it or remove it" in results.check(copy)


def test_a_sentence_that_narrates_history_fails(copy):
    stale(
        copy,
        "docs/study.md",
        "A study (`jaxafm.study.monte_carlo`",
        "This round a study (`jaxafm.study.monte_carlo`",
    )
    found = results.check(copy)
    assert len(found) == 1 and "docs/study.md" in found[0] and "'This round' narrates history" in found[0]
    stale(copy, "docs/study.md", "This round a study", "It took 7 min 58 s. A study")
    assert "'7 min 58 s' narrates history" in results.check(copy)[0]


def test_each_command_names_the_config_its_run_was_made_from():
    runs = [v for v in vars(results).values() if isinstance(v, results.Run)]
    runs += [run for _, run in results.DIAGNOSE_REAL]
    checked = 0
    for run in runs:
        manifest = (ROOT / run.file).parent / "jaxafm-run.json"
        if manifest.exists():
            config = Path(json.loads(manifest.read_text())["config_file"])
            if config.parent.name == "configs":
                assert f"configs/{config.name}" in run.command, run.file
                checked += 1
    assert checked >= 10


def test_numbers_print_with_their_units():
    assert results.q(10.433, "nm") == "10.4 nm"
    assert results.q(41152.97, "", 0) == "41,153"
    assert results.q(-0.0119, "°", 3) == "−0.012°"
    assert results.q(-0.01, "%") == "0.0 %"  # no negative zero
    assert results.q(2.5e-13, "%", 3, tiny=True) == "2.5e−13 %"
    assert results.q(None, "nm") == "–"
    assert results.span([8.9, 7.97], "%") == "8.0–8.9 %"
    assert results.span([-900.0, -536.0], "nm", 0) == "−900 to −536 nm"


def test_every_shipped_config_is_in_the_configs_table_and_every_row_is_shipped():
    """docs/cli.md's table of the shipped configs lists exactly the files in ``configs/``."""
    text = (ROOT / "docs" / "cli.md").read_text()
    table = text.split("## The shipped configs", 1)[1].split("\n## ", 1)[0]
    rows = {line.split("`")[1] for line in table.splitlines() if line.startswith("| `configs/")}
    shipped = {f"configs/{p.name}" for p in (ROOT / "configs").glob("*.yaml")}
    assert rows == shipped, (
        f"only in the table: {sorted(rows - shipped)}; not in it: {sorted(shipped - rows)}"
    )
