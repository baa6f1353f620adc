"""The README's Python snippets run as written, from the repository root."""

import re

from .conftest import REPO


def test_readme_python_snippets_run(monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), flags=re.S)
    assert len(blocks) >= 2
    monkeypatch.chdir(REPO)
    namespace: dict = {}
    for block in blocks:  # later snippets use the names of earlier ones, as a reader would
        exec(compile(block, "README.md", "exec"), namespace)
    result = namespace["result"]
    assert result.transformation.shape == (4, 4) and 0.0 <= result.confidence <= 1.0


def test_readme_results_tables_are_the_generated_ones():
    from benchmarks.results_table import markdown, scans_markdown

    text = (REPO / "README.md").read_text()
    commands = [c.split() for c in re.findall(r"Made by `python -m benchmarks.results_table ([^`]*)`", text.replace("\n", " "))]
    assert len(commands) == 2
    for command in commands:
        runs = [REPO / arg for arg in command if not arg.startswith("--")]
        marker = "scans" if "--scans" in command else "results"
        block = text.split(f"<!-- {marker}:start -->\n", 1)[1].split(f"\n<!-- {marker}:end -->", 1)[0]
        assert block == (scans_markdown(runs[0]) if marker == "scans" else markdown(runs, short="--short" in command))
