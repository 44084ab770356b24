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
        ROOT / "docs" / "paper_notes.md"]


def test_readme_has_the_blocks_it_promises():
    assert len(BLOCKS) >= 5
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
