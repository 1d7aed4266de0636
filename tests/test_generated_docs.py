"""Every table of numbers from runs in README.md and docs/ is a block that `python experiments/report.py --docs` writes
from the runs kept under docs/: each committed block must equal its rebuild, so no hand-typed number can drift from
the data."""

import difflib
import re

import pytest

import report
from tests.helpers import ROOT, run_cli


def test_every_generated_block_equals_its_rebuild_from_the_kept_runs():
    for path, rebuilt in report.rebuilt_pages().items():
        committed = path.read_text()
        diff = "\n".join(difflib.unified_diff(committed.splitlines(), rebuilt.splitlines(), "committed", "rebuilt",
                                              lineterm="", n=0))
        assert committed == rebuilt, (f"{path.relative_to(ROOT)} differs from its rebuild; run `python "
                                      f"experiments/report.py --docs` and commit:\n{diff[:3000]}")


def test_every_marker_in_the_docs_belongs_to_a_block_that_report_py_writes():
    blocks = {(page, name) for page, name, _ in report.DOCS_BLOCKS}
    marker = re.escape(report.BEGIN).replace(r"\{name\}", "(.+?)")
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        page = str(path.relative_to(ROOT))
        outside_code = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)  # an example in a code block is none
        for name in re.findall(marker, outside_code):
            assert (page, name) in blocks, f"{page}: block {name!r} has no row in report.DOCS_BLOCKS"


def test_a_hand_edited_number_and_a_missing_marker_are_found(tmp_path):
    page = tmp_path / "page.md"
    begin, end = report.BEGIN.format(name="t"), report.END.format(name="t")
    page.write_text(f"# Page\n\n{begin}\n| a |\n|---|\n| 1.5 |\n{end}\n\nText after.\n")
    blocks = [(str(page), "t", lambda: "| a |\n|---|\n| 1.5 |")]
    assert report.rebuilt_pages(blocks) == {page: page.read_text()}  # as committed: nothing to rewrite
    page.write_text(page.read_text().replace("1.5", "1.6"))
    assert report.rebuilt_pages(blocks)[page].count("| 1.5 |") == 1  # the rebuild puts the data's number back
    page.write_text(f"# Page\n\n{begin}\n| a |\n")
    with pytest.raises(report.ReportError, match="block 't' needs its two markers"):
        report.rebuilt_pages(blocks)


def test_report_py_docs_refuses_a_folder_and_a_report_needs_one(tmp_path):
    both = run_cli("experiments/report.py", str(tmp_path), "--docs")
    neither = run_cli("experiments/report.py", "--reps", "10")
    assert both.returncode == 2 and both.stderr.startswith("error: --docs takes no folder")
    assert neither.returncode == 2 and neither.stderr.startswith("error: give a folder of runs")
