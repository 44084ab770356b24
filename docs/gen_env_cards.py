"""Build one page per registered environment id ("env cards") from the code, for the docs site.

Run by mkdocs-gen-files (``mkdocs.yml``); the pages exist only in the built site. Everything on a
card is read from the code or the repository at build time, so a changed docstring, tier or
preset changes the card:

* the ids: every ``gym.registry`` entry whose entry point is in ``auv_follow_env``;
* the sections of the class docstring of ``auv_follow_env.env.AUVFollowEnv`` (observation and
  action tables, reward, start, episode end, info, arguments, rendering);
* the preset (``auv_follow_env.params.SCENARIOS``, ``DISTURBANCE_LEVELS``) or the tier
  (``auv_follow_env.tiers.TIERS``, ``tier_summary_markdown``, ``tier_table_markdown``);
* the episode length (``make_env_config(**kwargs).n_steps``) and the test seeds;
* the version history: the docstring's "Version History" and CHANGELOG.md's version policy and
  releases, read from the file.

``card_markdown(env_id)`` returns one card (``envs/<id>.md`` on the site); the table of cards is
appended to ``docs/envs.md``. The docs test calls these functions directly.
"""

from __future__ import annotations

import inspect
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CARD_DIR = "envs"
INDEX = "envs.md"  #: a page in docs/ to which the list of cards is appended
#: docstring sections shown on every card, in this order (the others are per version)
COMMON_SECTIONS = ("Description", "Action Space", "Observation Space", "Rewards", "Starting State", "Episode End",
                   "Info")
ISSUE_REF = re.compile(r"\s*\((?:[^()]*;\s*)?issue \d+\)|\bissue \d+'s\s+|\s*\(issue \d+[^)]*\)")


def registered_ids() -> list[str]:
    """Every registered id whose entry point is in ``auv_follow_env``, in registration order."""
    import gymnasium as gym

    import auv_follow_env  # noqa: F401  (registers the ids)

    out = []
    for env_id, spec in gym.registry.items():
        ep = spec.entry_point
        module = ep if isinstance(ep, str) else getattr(ep, "__module__", "")
        if module.split(":")[0].split(".")[0] == "auv_follow_env":
            out.append(env_id)
    return out


def card_path(env_id: str) -> str:
    return f"{CARD_DIR}/{env_id}.md"


# --- the class docstring -----------------------------------------------------------------

def _md(text: str) -> str:
    """reST roles and literal blocks of the docstring as Markdown."""
    text = re.sub(r":(?:class|func|mod|data|attr|meth):`~?([^`]+)`", lambda m: f"`{m.group(1)}`", text)
    # "text::" followed by an indented block: a fenced Python block
    def fence(m: re.Match) -> str:
        body = inspect.cleandoc(m.group(2))
        return f"{m.group(1)}:\n\n```python\n{body}\n```\n"
    return re.sub(r"([^\n]*?)::\n\n((?:    [^\n]*\n?|\n)+)", fence, text)


def docstring_sections(doc: str | None = None) -> dict[str, str]:
    """The ``## Title`` sections of the env's class docstring, title -> Markdown body."""
    if doc is None:
        from auv_follow_env.env import AUVFollowEnv

        doc = AUVFollowEnv.__doc__ or ""
    doc = inspect.cleandoc(doc)
    sections: dict[str, str] = {}
    parts = re.split(r"^## +(.+)$", doc, flags=re.M)
    sections["_summary"] = parts[0].strip()
    for title, body in zip(parts[1::2], parts[2::2], strict=True):
        sections[title.strip()] = _md(body.strip("\n")).strip()
    return sections


def _first_sentence(text: str) -> str:
    return re.split(r"(?<=[.!?])\s+(?=[A-Z])", " ".join(text.split()))[0]


def _demote(body: str) -> str:
    """Sub-headings of a section one level down (a section is a ``##`` on the card)."""
    return re.sub(r"^(#{2,5}) ", lambda m: "#" + m.group(1) + " ", body, flags=re.M)


# --- CHANGELOG.md ----------------------------------------------------------------------

def changelog_sections(text: str | None = None) -> list[tuple[str, str]]:
    """CHANGELOG.md as (heading, body) pairs, in file order."""
    if text is None:
        text = (ROOT / "CHANGELOG.md").read_text()
    parts = re.split(r"^## +(.+)$", text, flags=re.M)
    return [(h.strip(), b.strip()) for h, b in zip(parts[1::2], parts[2::2], strict=True)]


def _anchor(heading: str) -> str:
    """The anchor mkdocs' toc extension gives a heading."""
    slug = re.sub(r"[^\w\s-]", "", heading.lower()).strip()
    return re.sub(r"[-\s]+", "-", slug)


def _plain(sentence: str) -> str:
    """A CHANGELOG sentence without its references to the project's issue tracker."""
    return re.sub(r"\s{2,}", " ", ISSUE_REF.sub("", sentence)).strip()


def version_history(version: str, changelog: str | None = None, doc_history: str | None = None) -> str:
    """The version history of the ``-<version>`` ids: the docstring's entry, the CHANGELOG's
    version policy for them, the release that introduced them and the later releases' entries
    that name them (first sentence of each paragraph that does)."""
    fam = {"v0": r"\bv0\b|every id", "v1": r"\bv1\b|the tiers|tier id"}[version]
    lines = []
    if doc_history:
        for item in re.findall(r"^\* (.+?)(?=^\* |\Z)", doc_history, flags=re.M | re.S):
            if item.startswith(f"{version}:"):
                lines.append(f"* **{version}** (from the class docstring): {' '.join(item.split()[1:])}")
    sections = changelog_sections(changelog)
    for heading, body in sections:
        if heading.lower() == "version policy":
            for item in re.findall(r"^\* (.+?)(?=^\* |\Z)", body, flags=re.M | re.S):
                if item.startswith(f"**{version} ids**"):
                    lines.append(f"* Version policy ([CHANGELOG.md](../../CHANGELOG.md#{_anchor(heading)})): "
                                 + " ".join(item.split()))
    releases = [(h, b) for h, b in sections if h.lower() != "version policy"]
    introduced = None
    for heading, body in reversed(releases):  # oldest first
        if re.search(r"\b" + version + r"\b", body):
            introduced = heading
            first = re.split(r"(?<=[.!?])\s+(?=[A-Z])", " ".join(body.split()))[0]
            lines.append(f"* Introduced in **{heading}** ([CHANGELOG.md](../../CHANGELOG.md#{_anchor(heading)})): "
                         f"{_plain(first)}")
            break
    for heading, body in releases:
        if heading == introduced or introduced is None:
            continue
        found = []
        for para in re.split(r"\n\s*\n|^\* ", body, flags=re.M):
            first = re.split(r"(?<=[.!?])\s+(?=[A-Z])", " ".join(para.split()))[0]
            if first and re.search(fam, first):
                found.append(_plain(first))
        if found:
            lines.append(f"* **{heading}** ([CHANGELOG.md](../../CHANGELOG.md#{_anchor(heading)})):")
            lines += [f"    * {s}" for s in found]
    return "\n".join(lines)


# --- presets and tiers -------------------------------------------------------------------

def _scenario_table(name: str) -> str:
    from auv_follow_env.params import DISTURBANCE_LEVELS, SCENARIOS

    sc = SCENARIOS[name]
    lv = DISTURBANCE_LEVELS[sc.disturbance]
    t = sc.target
    rows = [("description", sc.description, "-"), ("delay tau", f"{sc.delay_s:g}", "s"),
            ("target mean speed v_bar", f"{t.speed:g}", "m/s"),
            ("surge modulation a_u, period P_u", f"{t.surge_amp:g}, {t.surge_period:g}", "-, s"),
            ("yaw-rate amplitude a_r, period P_r", f"{t.yaw_rate_amp:g}, {t.yaw_period:g}", "rad/s, s"),
            ("damping mismatch", f"{sc.mismatch:+.0%}".replace("%", " %"), "-"),
            ("disturbance level (default)", f"{lv.name} ({lv.description})", "-"),
            ("current x range", f"[{lv.current_x[0]:g}, {lv.current_x[1]:g}]", "m/s"),
            ("current y range", f"[{lv.current_y[0]:g}, {lv.current_y[1]:g}]", "m/s"),
            ("disturbance peaks d_u, d_v, d_r", ", ".join(f"{p:g}" for p in lv.peaks),
             "m/s^2, m/s^2, rad/s^2 (per unit mass)")]
    out = ["| parameter | value | unit |", "|---|---|---|"] + [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(out)


def _tier_block(name: str) -> str:
    from auv_follow_env.tiers import ALL_TIERS as TIERS
    from auv_follow_env.tiers import tier_summary_markdown, tier_table_markdown

    tier = TIERS[name]
    summary = tier_summary_markdown().splitlines()
    row = [line for line in summary[2:] if line.startswith(f"| `{tier.env_id}`")]
    full = tier_table_markdown()
    own = full.split(f"### {tier.env_id}:", 1)[1].split("\n### ", 1)[0]
    own = own.split("\n", 1)[1].strip()  # without the heading's description (shown above)
    return ("The fields that set the tier's difficulty (U[a, b]: drawn uniformly at every reset; "
            "`auv_follow_env.tiers.tier_summary_markdown()`):\n\n" + "\n".join(summary[:2] + row)
            + "\n\nEvery field the tier sets (`auv_follow_env.tiers.tier_table_markdown()`):\n\n" + own)


def _v0_test_seeds() -> tuple[int, ...]:
    from agents.benchmark.protocol import V0_TEST_SEEDS

    return tuple(V0_TEST_SEEDS)


def _seed_text(seeds: tuple[int, ...]) -> str:
    if seeds == tuple(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]} ({len(seeds)} seeds)"
    return ", ".join(map(str, seeds))


# --- one card ----------------------------------------------------------------------------

def card_markdown(env_id: str, doc: str | None = None, changelog: str | None = None) -> str:
    """The card of one registered id, as Markdown (``doc`` / ``changelog`` default to the code's
    docstring and the repository's CHANGELOG.md)."""
    import gymnasium as gym

    from auv_follow_env.tiers import ALL_TIERS as TIERS
    from auv_follow_env.tiers import make_env_config

    spec = gym.registry[env_id]
    kwargs = dict(spec.kwargs)
    sec = docstring_sections(doc)
    cfg = make_env_config(**kwargs)
    ts = cfg.task_spec()
    version = kwargs.get("version", "v0")
    tier = TIERS[kwargs["tier"]] if "tier" in kwargs else None
    scenario = kwargs.get("scenario")

    if tier is not None:
        what = f"Acoustic-link tier **{tier.name}**: {tier.description}."
        seeds = f"{_seed_text(tier.test_seeds)}: `auv_follow_env.ALL_TIERS[\"{tier.name}\"].test_seeds`"
        if tier.out_of_distribution:
            what += " Out of distribution: for testing only, never train or tune on it."
    elif scenario is not None:
        what = f"The paper's scenario **{scenario}** (Table 2), frozen."
        seeds = f"{_seed_text(_v0_test_seeds())} (our choice: `agents.benchmark.V0_TEST_SEEDS`)"
    elif version == "v1":
        what = ("A custom acoustic link: a scenario preset (`scenario=`, default S4) with the v1 link and "
                "observation; every link parameter is a `gym.make` keyword (no tier: nothing is drawn unless "
                "you give a `(min, max)` range).")
        seeds = ("none published (a custom task); `evaluate` and `compare` default to the first 10 of "
                 f"{_seed_text(_v0_test_seeds())}")
    else:
        what = "The paper's task with the scenario as a keyword (`scenario=\"S1\"` ... `\"S4\"`, default S4)."
        seeds = ("none published (a custom task); `evaluate` and `compare` default to the first 10 of "
                 f"{_seed_text(_v0_test_seeds())}")
    made = f"gym.make(\"{env_id}\")"
    kw = ", ".join(f"{k}={v!r}" for k, v in kwargs.items()) or "none"
    steps = f"{cfg.n_steps} ({cfg.episode_s:g} s at dt = {cfg.dt:g} s)"
    lines = [
        f"# {env_id}", "",
        what, "",
        "| | |", "|---|---|",
        f"| make | `{made}` (after `import auv_follow_env`, or `gym.make(\"auv_follow_env:{env_id}\")`) |",
        f"| vector env | `gym.make_vec(\"{env_id}\", num_envs=N)`: `{spec.vector_entry_point}` |",
        f"| registered keywords | `{kw}` |",
        f"| action space | `Box(-1, 1, (3,), float32)`: surge force, sway force, yaw moment as fractions of "
        f"`force_limits` = {tuple(float(f) for f in ts.force_limits)} N, N, N m |",
        f"| observation space | `Box(-inf, inf, ({ts.obs_dim},), float32)` (see below) |",
        f"| reward | {_first_sentence(sec.get('Rewards', '-'))} |",
        f"| episode length | {steps}; the env truncates itself: `max_episode_steps` = "
        f"{spec.max_episode_steps} in the registry |",
        f"| test seeds | {seeds} |",
        "",
        "The sections below are the class docstring of `auv_follow_env.env.AUVFollowEnv` "
        "([API reference](../api.md)), read when the site was built.", "",
    ]
    if tier is not None:
        lines += ["## Tier parameters", "", _tier_block(tier.name), ""]
    elif scenario is not None:
        lines += ["## Preset parameters", "", f"`auv_follow_env.params.SCENARIOS[\"{scenario}\"]` and its "
                  "disturbance level (`DISTURBANCE_LEVELS`):", "", _scenario_table(scenario), ""]
    for title in COMMON_SECTIONS:
        if title in sec:
            lines += [f"## {title}", "", _demote(sec[title]), ""]
    if version == "v1":
        v1 = next((t for t in sec if t.startswith("v1:")), None)
        if v1 is not None:
            lines += ["## What v1 changes: the acoustic link", "", _demote(sec[v1]), ""]
        if tier is None and "v1 parameters" in sec:
            lines += ["## v1 parameters", "", _demote(sec["v1 parameters"]), ""]
    elif "Scenarios (Table 2) and disturbance levels (Table 3)" in sec:
        lines += ["## Scenarios and disturbance levels", "",
                  _demote(sec["Scenarios (Table 2) and disturbance levels (Table 3)"]), ""]
    for title in ("Arguments", "Rendering"):
        if title in sec:
            lines += [f"## {title}", "", _demote(sec[title]), ""]
    lines += ["## Version history", "", version_history(version, changelog, sec.get("Version History")), ""]
    return "\n".join(lines)


def index_markdown(ids: list[str]) -> str:
    """The table of cards appended to docs/envs.md: one row per id, linking to its card."""
    import gymnasium as gym

    from auv_follow_env.tiers import ALL_TIERS as TIERS
    from auv_follow_env.tiers import make_env_config

    rows = ["", "| id | observation | what varies per reset | test seeds |", "|---|---|---|---|"]
    for env_id in ids:
        kw = dict(gym.registry[env_id].kwargs)
        cfg = make_env_config(**kw)
        if "tier" in kw:
            t = TIERS[kw["tier"]]
            varies = (f"the condition ({len(t.ranges)} fields drawn: {', '.join(t.ranges)}); the random target, "
                      "link, current and disturbances")
            seeds = _seed_text(t.test_seeds)
        elif kw.get("version") == "v1":
            varies = ("the phases as on v0, and the link, target and current processes you configure (a "
                      "`(min, max)` keyword is drawn per reset)")
        else:
            varies = "the phases of the target's manoeuvres, of the current and of the disturbances"
            seeds = _seed_text(_v0_test_seeds()) if "scenario" in kw else "-"
        rows.append(f"| [{env_id}]({card_path(env_id)}) | ({cfg.task_spec().obs_dim},) | {varies} | {seeds} |")
    return "\n".join(rows) + "\n"


def main() -> None:
    import mkdocs_gen_files

    ids = registered_ids()
    with mkdocs_gen_files.open(INDEX, "a") as f:  # docs/envs.md with the generated table appended
        f.write(index_markdown(ids))
    for env_id in ids:
        with mkdocs_gen_files.open(card_path(env_id), "w") as f:
            f.write(card_markdown(env_id))


if __name__ in ("__main__", "<run_path>"):
    main()
