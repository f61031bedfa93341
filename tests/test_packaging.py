"""The package's install surface: the core without the training extra, one version, the doctest fixture outside."""

import subprocess
import sys
from importlib import metadata
from pathlib import Path

import enmi_torch

ROOT = Path(__file__).resolve().parents[1]

# Blocks the training extra's packages, as on a machine with the core install only.
BLOCK_TRAINING = """
import sys
for name in ("lightning", "pytorch_lightning", "tensorboard", "jsonargparse"):
    sys.modules[name] = None
"""


def test_the_core_imports_without_the_training_extra():
    script = BLOCK_TRAINING + (
        "import enmi_torch, enmi_torch.data, enmi_torch.localization, enmi_torch.geometry, enmi_torch.variance\n"
        "from enmi_torch.data import SyntheticPairs, match_intensity\n"
        "print(sorted(n for n, m in sys.modules.items()\n"
        "             if m is not None and n.split('.')[0] in ('lightning', 'tensorboard')))\n"
        "try:\n"
        "    enmi_torch.data.PairDataModule\n"
        "except ImportError as error:\n"
        "    print('needs', error.name.split('.')[0])\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, check=True)
    assert result.stdout.split("\n")[:2] == ["[]", "needs lightning"], result.stdout + result.stderr


def test_the_training_command_names_the_missing_extra_in_one_line():
    script = BLOCK_TRAINING + "from enmi_torch.cli.fit_mask import main\nmain([])\n"
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "pip install -e '.[train]'" in result.stderr


def test_the_version_is_defined_once():
    assert metadata.version("enmi_torch") == enmi_torch.__version__
    citation = (ROOT / "CITATION.cff").read_text()
    assert f"\nversion: {enmi_torch.__version__}\n" in citation
    assert 'dynamic = ["version"]' in (ROOT / "pyproject.toml").read_text()


def test_the_installed_package_holds_no_test_fixture():
    assert not (Path(enmi_torch.__file__).parent / "conftest.py").exists()
