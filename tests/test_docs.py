"""The documentation site: it builds with warnings as errors in under a minute, every registered
id has an env card generated from the code, and the README and the pages speak in plain words
(no tracker issue numbers, no revision hashes: CHANGELOG.md keeps the history)."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def _generator():
    spec = importlib.util.spec_from_file_location("gen_env_cards", ROOT / "docs" / "gen_env_cards.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _registered_ids() -> list[str]:
    """Worked out here from the registry, independently of the generator's own filter."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401

    return [k for k, s in gym.registry.items() if str(s.entry_point).startswith("auv_follow_env.")]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "DISABLE_MKDOCS_2_WARNING": "true", "NO_MKDOCS_2_WARNING": "1"}
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300, env=env)
    elapsed = time.perf_counter() - t0
    assert res.returncode == 0, f"mkdocs build --strict failed:\n{res.stderr[-4000:]}"
    return out, elapsed


def test_site_builds_strict_in_under_a_minute(site):
    out, elapsed = site
    assert elapsed < 60, f"the docs build took {elapsed:.1f} s"
    for page in ("index.html", "getting_started/index.html", "tiers/index.html", "benchmark/index.html",
                 "floors/index.html", "training/index.html", "reproduction/index.html", "paper_notes/index.html",
                 "performance/index.html", "interop/index.html", "api/index.html", "examples/index.html"):
        assert (out / page).is_file(), page
    # repository files the pages link to are on the site too (copied by docs/hooks/repo_links.py)
    for copied in ("CHANGELOG/index.html", "results/floors/floors/index.html", "results/benchmark/leaderboard.png",
                   "examples/user_controller.py"):
        assert (out / copied).is_file(), copied
    # the API reference is rendered from the docstrings
    api = (out / "api" / "index.html").read_text()
    assert "AUVFollowEnv" in api and "evaluate_batched" in api and "check_training_seeds" in api


def test_every_registered_id_has_a_card(site):
    from auv_follow_env import TIERS

    out, _ = site
    ids = _registered_ids()
    assert len(ids) == 13  # S1-S4, v0, four tiers, three Leader tiers, v1
    index = (out / "envs" / "index.html").read_text()
    for env_id in ids:
        page = out / "envs" / env_id / "index.html"
        assert page.is_file(), f"no card for {env_id}"
        text = page.read_text()
        assert env_id in text and "Version history" in text and f'href="{env_id}/"' in index
    hard = (out / "envs" / "AUVFollow-Hard-v1" / "index.html").read_text()
    seeds = TIERS["Hard"].test_seeds
    assert (seeds[0], seeds[-1]) == (3000000, 3000099) and "3000000-3000099" in hard
    leader = (out / "envs" / "AUVFollow-Leader-Hard-v1" / "index.html").read_text()
    assert "7000000-7000099" in leader and "leader_uturn_rate" in leader


def test_every_card_is_in_the_nav():
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]
    flat = re.findall(r"envs/[\w.-]+\.md", str(nav))
    assert sorted(flat) == sorted(f"envs/{i}.md" for i in _registered_ids())


def test_card_is_generated_from_the_docstring(monkeypatch):
    from auv_follow_env.env import AUVFollowEnv

    gen = _generator()
    before = gen.card_markdown("AUVFollow-S4-v0")
    assert "## Rewards" in before and "Num | Name | Unit" in before  # the docstring's sections and tables
    doc = AUVFollowEnv.__doc__
    new = re.sub(r"(## Rewards\n\n)", r"\1    Sentinel reward sentence for the docs test.\n\n", doc, count=1)
    assert new != doc
    monkeypatch.setattr(AUVFollowEnv, "__doc__", new)
    after = gen.card_markdown("AUVFollow-S4-v0")
    assert "Sentinel reward sentence for the docs test." in after
    assert "Sentinel reward sentence" not in before


def test_card_shows_the_tier_and_preset_from_the_code():
    gen = _generator()
    hard = gen.card_markdown("AUVFollow-Hard-v1")
    # auv_follow_env/tiers.py, by hand: Hard's fix period U[2, 4] s, fixed thruster lag 0.3 s, seeds 3,000,000 + 0..99
    assert "| update_period_s | U[2, 4] | s |" in hard and "| thruster_tc_s | 0.3 | s |" in hard
    assert "3000000-3000099 (100 seeds)" in hard and "1200 (60 s at dt = 0.05 s)" in hard
    assert "(20,)" in hard
    s2 = gen.card_markdown("AUVFollow-S2-v0")
    # auv_follow_env/params.py, by hand: S2 has a 1 s delay, level L1, +60 % damping mismatch; 16 fields
    assert "| delay tau | 1 | s |" in s2 and "L1 (mild)" in s2 and "+60 %" in s2 and "(16,)" in s2


def test_version_history_is_read_from_the_changelog():
    gen = _generator()
    log = ("# Changelog\n\n## Version policy\n\n* **v1 ids** are frozen per version.\n\n"
           "## 9.9.9\n\nThe v1 tiers gained a sentinel feature. Something else.\n\n"
           "## 0.1.0\n\nThe environments (v0 and the v1 tiers) first appeared.\n")
    card = gen.card_markdown("AUVFollow-Easy-v1", changelog=log)
    history = card.split("## Version history", 1)[1]
    assert "**v1 ids** are frozen per version." in history
    assert "Introduced in **0.1.0**" in history and "**9.9.9**" in history
    assert "The v1 tiers gained a sentinel feature." in history and "Something else" not in history
    assert "sentinel" not in gen.card_markdown("AUVFollow-S1-v0", changelog=log).lower()


# --- plain words: no issue numbers, no revision hashes ------------------------------------------

ISSUE = re.compile(r"\bissues? #?\d+|(?:^|[\s(\[,;])#\d+\b", re.I | re.M)
# 7-40 hex digits with at least one letter a-f and one digit: a git revision (not a number or a word)
HASH = re.compile(r"(?<![.\d])\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b(?![-+])")


def _user_facing_files() -> list[Path]:
    return [ROOT / "README.md", ROOT / "mkdocs.yml"] + sorted((ROOT / "docs").rglob("*.md"))


def _code_files() -> list[Path]:
    """Code (comments and docstrings included) and the developers' pages: they explain in their
    own words too. This file is left out: its pattern test holds examples of what is refused."""
    code = [p for d in ("auv_follow_env", "controllers", "agents", "experiments", "examples", "docs", "tests",
                        "scripts") for p in sorted((ROOT / d).rglob("*")) if p.suffix in (".py", ".sh", ".md", ".yml")]
    return [p for p in code + [ROOT / "DEVELOPERS.md", ROOT / "pyproject.toml"]
            if p.name != "test_docs.py" and p not in _user_facing_files()]


def test_the_patterns_catch_what_they_should():
    assert ISSUE.search("the default until issue 23") and ISSUE.search("see (#12)") and ISSUE.search("Issues 4")
    assert HASH.search("against 3c1117b in one run") and HASH.search("main c8bca84")
    assert not ISSUE.search("[link](page.md#010)") and not HASH.search("seeds 3000000-3000099, 1e-9, deadline")
    assert not HASH.search("pio2 = 6.36619772367581382433e-01")  # a number literal, not a revision


@pytest.mark.parametrize("path", _user_facing_files() + _code_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_issue_numbers_or_hashes(path):
    text = path.read_text()
    found = [m.group(0).strip() for m in ISSUE.finditer(text)] + [m.group(0) for m in HASH.finditer(text)]
    assert not found, f"{path.relative_to(ROOT)} refers to {found}: say it in plain words (CHANGELOG.md keeps history)"


# --- the code on the pages runs ----------------------------------------------------------------

def _blocks(page: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", (ROOT / "docs" / page).read_text(), flags=re.S | re.M)


PAGE_BLOCKS = [(page, i) for page in ("interop.md", "getting_started.md", "training.md", "data.md")
               for i in range(len(_blocks(page)))]


@pytest.mark.parametrize("page,index", PAGE_BLOCKS, ids=[f"{p}-{i}" for p, i in PAGE_BLOCKS])
def test_page_python_block_runs_alone(page, index):
    code = _blocks(page)[index]
    for module in re.findall(r"^from (torchrl|skrl)\b", code, flags=re.M):
        pytest.importorskip(module, reason=f"{module} is not installed (pip install -e '.[dev]')")
    env = {**os.environ, "MPLBACKEND": "Agg"}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 0, f"{page} block {index} failed:\n{code}\n--- stderr ---\n{out.stderr[-3000:]}"
