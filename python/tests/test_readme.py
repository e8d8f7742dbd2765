"""The README's Python example runs as written."""

import os
import re

from conftest import REPO


def test_readme_example_runs(tmp_path, monkeypatch):
    text = (REPO / "README.md").read_text()
    section = text[text.index("## Python"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["report"]["frames"] == 1
    assert namespace["out_coords"].shape == (2, 4) and namespace["out_feats"].shape == (2, 8)
    assert os.path.exists("pred/sequences/08/predictions/000000.label")
