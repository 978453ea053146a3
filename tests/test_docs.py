"""The docs a user reads agree with the code: docs/config.md is what the config classes generate,
and the README's preset tables list exactly the presets `relayrl presets` lists."""

import re
from pathlib import Path

from relayrl.agents.registry import ALGORITHMS
from relayrl.docs_config import render
from relayrl.presets import list_presets

ROOT = Path(__file__).resolve().parents[1]


def preset_tables(markdown: str) -> list[list[str]]:
    """The first-column names of every table whose header's first cell is `preset`."""
    tables, current = [], None
    for line in markdown.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else None
        if cells is None:
            current = None
        elif cells[0] == "preset":
            current = []
            tables.append(current)
        elif current is not None and not set(cells[0]) <= set("-: "):
            match = re.fullmatch(r"`([^`]+)`", cells[0])
            current.append(match.group(1) if match else cells[0])
    return tables


def test_config_reference_is_current():
    assert (ROOT / "docs" / "config.md").read_text() == render(), "run `python -m relayrl.docs_config`"


def test_config_reference_covers_every_section_and_algorithm():
    text = render()
    for name in ("env", "train", "eval", "replay", "distributed"):
        assert f"## [{name}]" in text, name
    for algo in ALGORITHMS:
        assert f'### [agent] with algo = "{algo}"' in text, algo
    for key in ("`seed`", "`env.num_workers`", "`replay.device`", "`distributed.actor_cpus`",
                "`agent.double`", "`agent.network`", "`agent.target_entropy`",
                "`agent.gae_lambda`", "`agent.rollout_steps`"):
        assert key in text, key


def test_config_reference_lists_stable_baselines3_names():
    # A user porting RL Zoo's hyperparameter files met these only as error messages.
    from relayrl.config_fields import SB3_NAMES

    text = render()
    assert "## Stable-Baselines3 and RL Zoo names" in text
    for name in ("target_update_interval", "gradient_steps", "exploration_fraction", "n_steps", *SB3_NAMES):
        assert f"| `{name}` |" in text, name


def test_config_reference_lists_cleanrl_names():
    from relayrl.config_fields import CLEANRL_NAMES

    text = render()
    assert "## CleanRL names" in text and "CleanRL's `vf_coef = 0.5` is `agent.vf_coef = 0.25`" in text
    for name in CLEANRL_NAMES:
        assert f"| `{name}` |" in text, name


def test_readme_preset_tables_list_exactly_the_presets():
    tables = preset_tables((ROOT / "README.md").read_text())
    assert tables, "the README has no table whose first column is `preset`"
    names = sorted(list_presets())
    for table in tables:
        assert sorted(table) == names, (sorted(set(table) ^ set(names)), "README table vs `relayrl presets`")


def anchor(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_benchmark_links_point_at_sections():
    for name in ("benchmarks.md", "distributed.md"):
        text = (ROOT / "docs" / name).read_text()
        anchors = {anchor(h) for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}
        links = re.findall(r"\]\(#([^)]+)\)", text)
        assert links or name != "benchmarks.md"
        assert not [a for a in links if a not in anchors], name


def test_summary_rows_link_to_their_sections():
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    summary = text.split("## Summary", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in summary.splitlines() if line.startswith("| [")]
    assert len(rows) >= 10 and all("](#" in row.split("|")[1] for row in rows)


def test_readme_links_to_benchmark_sections_resolve():
    readme = (ROOT / "README.md").read_text()
    text = (ROOT / "docs" / "benchmarks.md").read_text()
    anchors = {anchor(h) for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}
    links = re.findall(r"\(docs/benchmarks\.md#([^)]+)\)", readme)
    assert links and not [a for a in links if a not in anchors]
    own = {anchor(h) for h in re.findall(r"^#+ (.+)$", readme, flags=re.M)}
    assert not [a for a in re.findall(r"\]\(#([^)]+)\)", readme) if a not in own]


def test_loaded_policy_docs_give_actions_in_the_env_action_shape():
    """A Box action [2, 2] comes out of a loaded or exported policy as [2, 2] ([B, 2, 2] for a
    batch: tests/test_spaces.py); the docs that promised [A] / [B, A] misled users of such envs."""
    import relayrl.export
    import relayrl.loaded_policy

    readme = " ".join((ROOT / "README.md").read_text().split())
    assert "a batch `[B, *obs_shape]` in, `[B]` or `[B, *action_shape]` out" in readme
    for doc in (relayrl.export.__doc__, relayrl.export.load_policy.__doc__, relayrl.loaded_policy.LoadedPolicy.__doc__):
        text = " ".join(doc.split())
        assert "[B, *action_shape]" in text and "[B, A]" not in text
    assert "greedy in Q" not in relayrl.export.load_policy.__doc__  # PPO's discrete action is its most likely one


def test_readme_run_directory_names_every_column_of_an_evaluation_row(tmp_path):
    import relayrl

    cfg = relayrl.load_config("dqn", ["train.total_steps=200", "eval.interval=0", "eval.episodes=1"])
    row = relayrl.train(cfg, tmp_path / "r", progress=False).final
    listing = (ROOT / "README.md").read_text().split("RUN_DIR/metrics.jsonl", 1)[1].split("RUN_DIR/tb/", 1)[0]
    named = set(re.findall(r"[\w/]+", listing))
    missing = [k for k in row if k not in named and k.split("/")[0] + "/..." not in listing]
    assert not missing, f"metrics.jsonl columns the README's run directory listing does not name: {missing}"


def test_readme_says_predict_defaults_otherwise_than_sb3s():
    """SB3's model.predict(obs) samples; a loaded policy's predict(obs) acts as it was loaded
    (greedy by default): a ported script's bare predict changes meaning, and the README says so."""
    import relayrl.loaded_policy as lp

    text = " ".join((ROOT / "README.md").read_text().split())
    assert "Stable-Baselines3's `predict` defaults to `deterministic=False`" in text
    assert "deterministic: bool | None = None" in Path(lp.__file__).read_text()  # still the loaded mode's default


def test_the_config_reference_is_written_where_the_checkout_keeps_it_from_any_folder(tmp_path, monkeypatch):
    from relayrl import docs_config

    assert docs_config.DEFAULT_OUT == ROOT / "docs" / "config.md"  # the checkout's, not the folder's
    out = tmp_path / "docs" / "config.md"
    out.parent.mkdir()
    monkeypatch.setattr(docs_config, "DEFAULT_OUT", out)
    monkeypatch.chdir(tmp_path.parent)
    assert docs_config.main([]) == 0 and out.read_text() == render()
    out.write_text("kept")
    assert docs_config.main(["--help"]) == 0 and out.read_text() == "kept"  # arguments write nothing
    assert docs_config.main(["docs"]) == 2 and out.read_text() == "kept"
