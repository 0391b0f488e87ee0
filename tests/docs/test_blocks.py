"""The documentation: the site builds with warnings as errors, every shell and Python block of
the README and the pages is run by a named test (or says what it needs), and the README's
quick start runs on the generated world."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RUNNABLE = re.compile(r"^```(bash|console|python|sh)\s*$")
MARK = re.compile(r"^<!-- block: (run by (?P<by>\S+)( .+)?|needs .+|long .+) -->$")


def blocks(page: Path) -> list[tuple[int, str, str]]:
    """``(line, marker line, code)`` of every runnable fenced block of ``page``."""
    lines = page.read_text().splitlines()
    out = []
    for i, line in enumerate(lines):
        if RUNNABLE.match(line):
            end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
            out.append((i + 1, lines[i - 1] if i else "", "\n".join(lines[i + 1 : end]) + "\n"))
    return out


def unmarked(page: Path) -> list[str]:
    """The blocks of ``page`` that neither a test runs nor say what they need, as problems."""
    text = page.read_text()
    if "<!-- blocks: every one run by tests/docs/test_walkthrough.py -->" in text:
        return []
    problems = []
    for line, mark, _ in blocks(page):
        m = MARK.match(mark)
        if m is None:
            problems.append(f"{page.name}:{line}: a block with no '<!-- block: ... -->' line above it")
        elif m.group("by") and not (ROOT / m.group("by")).is_file():
            problems.append(f"{page.name}:{line}: run by {m.group('by')}, which does not exist")
    return problems


def test_every_block_is_run_by_a_test_or_says_what_it_needs():
    problems = [p for page in PAGES for p in unmarked(page)]
    assert problems == []


def test_an_unmarked_block_is_found(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("text\n\n```bash\nhogsa demo\n```\n\n<!-- block: run by tests/nowhere.py -->\n```python\nx\n```\n")
    assert [p.split(": ", 1)[1] for p in unmarked(page)] == [
        "a block with no '<!-- block: ... -->' line above it",
        "run by tests/nowhere.py, which does not exist",
    ]


def test_the_readme_quick_start_runs_on_the_generated_world(tiny_world, untrained_bundle, tmp_path):
    (code,) = [c for _, m, c in blocks(ROOT / "README.md") if "tests/docs/test_blocks.py" in m]
    assert 'ArcticDataset("data"' in code and '"build/bundle"' in code
    (tmp_path / "data").symlink_to(tiny_world, target_is_directory=True)
    (tmp_path / "build").mkdir()
    (tmp_path / "build" / "bundle").symlink_to(untrained_bundle, target_is_directory=True)
    # on the CPU, one epoch, one batch of it
    code = code.replace('device="cuda"', 'device="cpu"').replace("range(10)", "range(1)").replace("num_workers=4", "")
    code = code.replace("        ...\n", "        print('batch', len(meta_info['imgname']))\n        break\n")
    script = tmp_path / "quick_start.py"
    script.write_text(code)
    env = {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK")}
    proc = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "batch 64" in proc.stdout


@pytest.mark.parametrize("page", ["README.md"])
def test_the_readme_is_a_front_door(page):
    lines = (ROOT / page).read_text().splitlines()
    assert len(lines) <= 250
    for heading in ("## Install", "## Quick start", "## Results", "## Limitations", "## License", "## Citation"):
        assert any(line.startswith(heading) for line in lines), heading


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    for page in ("index.html", "real-arctic/index.html", "results/index.html", "cli/index.html", "api/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    cli = (tmp_path / "site" / "cli" / "index.html").read_text()
    assert "hogsa frame-maps" in cli and "--allow-held-out" in cli  # generated from the parsers
    assert "wrap_train_loader" in (tmp_path / "site" / "api" / "index.html").read_text()
