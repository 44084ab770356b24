"""The README works from a clone: every ```python block runs on its own in a fresh interpreter
(from the repository root), and no document links outside the repository."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BLOCKS = re.findall(r"^```python\n(.*?)^```", README.read_text(), flags=re.S | re.M)
DOCS = [README, ROOT / "DEVELOPERS.md", ROOT / "agents" / "README.md", ROOT / "results" / "paper" / "claims.md",
        *sorted((ROOT / "docs").rglob("*.md"))]


def test_readme_is_short_and_its_lines_fit():
    lines = README.read_text().splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines: move detail to docs/"
    long = [i + 1 for i, line in enumerate(lines) if len(line) > 200]
    assert not long, f"README.md lines over 200 characters: {long}"


def test_the_newcomers_path_is_on_the_first_screen():
    """Install, a first episode, what observation and action mean, and a first leaderboard, in
    the first 60 lines."""
    first = "\n".join(README.read_text().splitlines()[:60])
    for needle in ("bash scripts/reproduce.sh", "bash scripts/test.sh", "pip install", "env.reset(seed=",
                   "env.step(action)", "**Action**", "**Observation**", "**Reward**", "auv-follow benchmark"):
        assert needle in first, needle


def test_readme_lists_every_registered_id():
    import gymnasium as gym

    import auv_follow_env  # noqa: F401

    text = README.read_text()
    ids = [k for k, s in gym.registry.items() if str(s.entry_point).startswith("auv_follow_env.")]
    rows = [line for line in text.splitlines() if line.startswith("| `AUVFollow-")]
    missing = [i for i in ids if not any(f"`{i}`" in r or f"`-{i.removeprefix('AUVFollow-')}`" in r for r in rows)]
    assert not missing, f"README.md's table of ids lacks {missing}"


def test_readme_has_the_blocks_it_promises():
    assert len(BLOCKS) >= 4
    joined = "\n".join(BLOCKS)
    for needle in ("evaluate_batched(", "help(auv_follow_env.env.AUVFollowEnv)", "load_agent(", "evaluate("):
        assert needle in joined, needle


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_block_runs_alone(index):
    code = BLOCKS[index]
    env = {**os.environ, "MPLBACKEND": "Agg", "PAGER": "cat"}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env=env)
    assert out.returncode == 0, f"README block {index} failed:\n{code}\n--- stderr ---\n{out.stderr[-3000:]}"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_documents_link_only_inside_the_repository(doc):
    text = doc.read_text()
    assert "../shared" not in text and "shared/paper" not in text
    for target in re.findall(r"\]\(([^)#\s]+)\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        assert (doc.parent / target).resolve().is_file(), f"{doc.name} links to missing {target}"


def test_the_readme_commands_work_in_a_fresh_shell_after_the_set_up():
    """As a newcomer types them after `bash scripts/setup.sh`: a login-less shell with only the system
    PATH, the README's activation line, then the README's first commands (they failed with `auv-follow: command
    not found`, then "No module named 'gymnasium'")."""
    text = README.read_text()
    activate = re.search(r"^(\. \.venv/bin/activate)\b", text, flags=re.M)
    assert activate, "README.md gives no line that activates .venv"
    if not (ROOT / ".venv" / "bin" / "activate").is_file():
        pytest.skip("no .venv in this checkout (the README's set-up makes it)")
    script = f"{activate.group(1)} && auv-follow --help >/dev/null && python -c 'import gymnasium, auv_follow_env'"
    out = subprocess.run(["env", "-i", "PATH=/usr/bin:/bin", f"HOME={os.environ.get('HOME', '/tmp')}", "bash",
                          "--noprofile", "--norc", "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
