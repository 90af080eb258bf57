"""scripts/doc_outputs.py: the marked blocks of a Markdown page are found, compared and replaced as documented.

Only the script's pure functions are tested here (no command is run: unit tests start no process); CI runs
``scripts/doc_outputs.py --check`` on README.md and docs/ itself.
"""

import importlib.util
import sys

import pytest

from ..conftest import ROOT

spec = importlib.util.spec_from_file_location("doc_outputs", ROOT / "scripts" / "doc_outputs.py")
doc_outputs = importlib.util.module_from_spec(spec)
sys.modules.setdefault("doc_outputs", doc_outputs)  # dataclasses look their module up there
spec.loader.exec_module(doc_outputs)

PAGE = """# A page

<!-- magkf-output: magkf sinefit --curves data/c.json -->
```
sine-fit calibration (paper)
  kx 0.909
```

Some text.

<!-- magkf-session -->
```
$ magkf simulate drive -o d.csv
wrote 10 rows to d.csv
$ magkf calibrate d.csv -o c.json --quiet | head -2
ekf calibration (both), 60000 epochs in 0.69 s (86,363 epochs/s); start: bootstrap-vector
  b  +594.87 +- 40.18 nT
```

<!-- magkf-setup -->
```python
print("made")
```

<!-- magkf-example: a user's own ROS bag -->
```
$ magkf check my.bag
format ros1-bag
```

```
$ magkf check unmarked.csv
```

```toml
[not] = "an output"
```
"""


def test_blocks_found_with_their_markers_and_lines():
    blocks = doc_outputs.parse_blocks(PAGE)
    assert [(b.kind, b.argument) for b in blocks] == [
        ("output", "magkf sinefit --curves data/c.json"),
        ("session", ""),
        ("setup", ""),
        ("example", "a user's own ROS bag"),
        ("unmarked", ""),
    ]
    lines = PAGE.split("\n")
    first = blocks[0]
    assert lines[first.first - 1] == "```" and lines[first.first] == "sine-fit calibration (paper)"
    assert lines[first.last] == "  kx 0.909" and lines[first.last + 1] == "```"
    assert blocks[2].info == "python"


def test_session_commands_and_rebuilt_body():
    session = doc_outputs.parse_blocks(PAGE)[1]
    commands = doc_outputs.session_commands(session.body)
    assert commands == ["magkf simulate drive -o d.csv", "magkf calibrate d.csv -o c.json --quiet | head -2"]
    body = doc_outputs.session_body(commands, ["wrote 10 rows to d.csv\n", "line 1\nline 2\n"])
    assert body == ["$ " + commands[0], "wrote 10 rows to d.csv", "$ " + commands[1], "line 1", "line 2"]
    assert doc_outputs.session_body(["true"], [""]) == ["$ true"]  # a silent command keeps its prompt line


def test_marker_without_a_block_and_unclosed_block_are_refused():
    with pytest.raises(ValueError, match="line 2: a magkf-output marker must be followed"):
        doc_outputs.parse_blocks("text\n<!-- magkf-output: magkf check x -->\n\n```\nx\n```\n")
    with pytest.raises(ValueError, match="never closed"):
        doc_outputs.parse_blocks("<!-- magkf-session -->\n```\n$ magkf check x\n")


def test_run_time_port_memory_and_tmp_normalised_but_figures_kept():
    shown = [
        "ekf calibration (both), 60000 epochs in 0.69 s (86,363 epochs/s); start",
        "  peak memory per worker: tls://127.0.0.1:39771 207 MB (limit 12638 MB)",
        "  written to /tmp/magkf-docs-x/repo/out.csv   ",
    ]
    produced = [
        "ekf calibration (both), 60000 epochs in 1.02 s (58,823 epochs/s); start",
        "  peak memory per worker: tls://127.0.0.1:41001 215 MB (limit 12000 MB)",
        "  written to /tmp/magkf-docs-y/repo/out.csv",
    ]
    shown[2] = shown[2].replace("/tmp/magkf-docs-x/repo", "<tmp>")
    assert doc_outputs.compare(shown, produced, "page.md:3", tmp="/tmp/magkf-docs-y/repo") == ""
    fewer_epochs = [produced[0].replace("60000 epochs", "59999 epochs"), *produced[1:]]
    assert "59999 epochs" in doc_outputs.compare(shown, fewer_epochs, "page.md:3", tmp="/tmp/magkf-docs-y/repo")


def test_changed_figure_fails_with_a_diff():
    shown = ["  residual RMS 230.77 nT over the 55578 epochs used", "  epochs: used 55578, gated_innovation 493"]
    produced = ["  residual RMS 230.77 nT over the 55578 epochs used", "  epochs: used 55578, gated_innovation 161"]
    diff = doc_outputs.compare(shown, produced, "docs/tutorial.md:19")
    assert "--- docs/tutorial.md:19 (shown)" in diff
    assert "-  epochs: used 55578, gated_innovation 493" in diff
    assert "+  epochs: used 55578, gated_innovation 161" in diff
    assert doc_outputs.compare(shown, shown, "x") == ""


def test_bodies_replaced_and_the_rest_of_the_page_kept():
    blocks = doc_outputs.parse_blocks(PAGE)
    runnable = [b for b in blocks if b.kind in ("output", "session")]
    bodies = {runnable[0].first: ["new output", "two lines"], runnable[1].first: ["$ magkf simulate drive"]}
    text = doc_outputs._replace_bodies(PAGE, runnable, bodies)
    again = doc_outputs.parse_blocks(text)
    assert again[0].body == ["new output", "two lines"]
    assert again[1].body == ["$ magkf simulate drive"]
    assert [b.body for b in again[2:]] == [b.body for b in blocks[2:]]
    assert text.replace("new output\ntwo lines", "").count("Some text.") == 1
