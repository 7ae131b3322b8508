"""The README's Python snippets are the runnable examples, as written (tests/test_examples.py
runs them)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FENCE = re.compile(r"^```python\n(.*?)^```$", re.S | re.M)


def test_every_python_snippet_of_the_readme_is_an_example_file_verbatim() -> None:
    snippets = FENCE.findall((ROOT / "README.md").read_text())
    examples = {p.read_text(): p.name for p in (ROOT / "examples").glob("*.py")}
    assert snippets, "the README shows no Python snippet"
    assert [examples.get(s) for s in snippets] == ["plugin.py", "env_route.py"]
