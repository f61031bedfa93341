"""The layout check finds each kind of finding in a small tree made to hold it, and none in a clean one."""

from pathlib import Path

import pytest

from data_tools.checks.check_layout import MAX_FILE_LINES, findings_of, main

WIDE = "def wide(" + ", ".join(f"a{i}" for i in range(14)) + ", *, b=1, **options):\n    pass\n"
MANY = f"__all__ = {[f'n{i}' for i in range(26)]}\n" + "".join(f"n{i} = {i}\n" for i in range(26))
CYCLE = "import cycle among enmi_torch.scores, enmi_torch.tracking"
ANNOTATION_ONLY = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import enmi_torch.tracking\n"
CLEAN = {
    "enmi_torch/__init__.py": '__all__ = ["Thing"]\nfrom enmi_torch.things import Thing\n',
    "enmi_torch/things.py": "class Thing:\n    pass\n\n\ndef helper(a, b, *, c=1):\n    return a\n",
    "enmi_torch/scores/__init__.py": "",
    "enmi_torch/scores/ecr.py": "class ECR:\n    pass\n\n\ndef is_ecr(x):\n    return isinstance(x, ECR)\n",
    "enmi_torch/tracking/__init__.py": "from enmi_torch.scores.ecr import ECR\n",
    "README.md": "# a library\n" * 10,
}


def _tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def test_a_clean_tree_has_no_finding(tmp_path):
    assert findings_of(_tree(tmp_path, CLEAN)) == []


@pytest.mark.parametrize(
    ("changes", "finding"),
    [
        ({"enmi_torch/tracking/step.py": "from enmi_torch.scores.ecr import _private\n"}, "private name _private"),
        ({"enmi_torch/tracking/step.py": "from ..scores.ecr import _private\n"}, "imported from enmi_torch.scores.ecr"),
        (
            {"enmi_torch/tracking/step.py": "from enmi_torch.scores.ecr import ECR\nisinstance(1, (int, ECR))\n"},
            "isinstance on the score family ECR outside enmi_torch/scores/ecr.py",
        ),
        ({"enmi_torch/big.py": "x = 1\n" * (MAX_FILE_LINES + 1)}, f"{MAX_FILE_LINES + 1} lines"),
        ({"enmi_torch/wide.py": WIDE}, "wide takes 16 parameters"),
        ({"enmi_torch/scores/nmi.py": "import enmi_torch.tracking\n"}, CYCLE),
        ({"README.md": "line\n" * 151}, "README.md: 151 lines"),
        ({"enmi_torch/__init__.py": "__all__ = ['Thing', 'Gone']\nfrom enmi_torch.things import Thing\n"}, "Gone"),
        ({"enmi_torch/__init__.py": MANY}, "holds 26 names"),
    ],
)
def test_each_kind_of_finding_is_named(tmp_path, changes, finding):
    found = findings_of(_tree(tmp_path, {**CLEAN, **changes}))
    assert any(finding in line for line in found), found


def test_an_import_for_annotations_only_makes_no_cycle(tmp_path):
    assert findings_of(_tree(tmp_path, {**CLEAN, "enmi_torch/scores/nmi.py": ANNOTATION_ONLY})) == []


def test_the_command_exits_1_with_findings_and_0_without(tmp_path, capsys):
    assert main(["--root", str(_tree(tmp_path / "clean", CLEAN))]) == 0
    assert capsys.readouterr().out.strip() == "check_layout: 0 finding(s)"
    assert main(["--root", str(_tree(tmp_path / "long", {**CLEAN, "README.md": "line\n" * 151}))]) == 1
    assert "README.md: 151 lines" in capsys.readouterr().out
