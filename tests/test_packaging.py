"""The package's install surface: the core without the training extra, one version, the doctest fixture outside."""

import os
import shutil
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

import enmi_torch
from enmi_torch.utils.resources import config_dir, config_file

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


def test_every_package_folder_is_listed_and_configs_install_from_the_top_level_folder():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11 and later
    settings = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {".".join(path.parent.relative_to(ROOT).parts) for path in (ROOT / "enmi_torch").rglob("__init__.py")}
    listed = set(settings["packages"])
    assert folders <= listed, f"add {sorted(folders - listed)} to [tool.setuptools] packages in pyproject.toml"
    assert settings["package-dir"] == {"enmi_torch.configs": "configs"}
    assert not (ROOT / "enmi_torch" / "configs").exists()  # one copy: the top-level configs/
    shipped = {f"{package}:{pattern}" for package, patterns in settings["package-data"].items() for pattern in patterns}
    for path in (ROOT / "configs").rglob("*"):
        if path.is_file() and path.suffix in (".yaml", ".csv"):
            folder = path.parent.relative_to(ROOT / "configs").parts
            package = ".".join(("enmi_torch", "configs", *folder))
            assert f"{package}:*{path.suffix}" in shipped, f"{path} is not shipped as package data"


def test_default_configs_are_the_clones_in_a_source_tree():
    assert config_dir() == ROOT / "configs"
    assert config_file("camera/paper.yaml") == ROOT / "configs" / "camera" / "paper.yaml"
    with pytest.raises(FileNotFoundError, match=r"'nothing\.yaml' is missing"):
        config_file("nothing.yaml")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    pytest.importorskip("build")
    folder = tmp_path_factory.mktemp("wheel")
    source = folder / "source"  # a copy of the tracked files: no build/ left over from another build
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    for name in files:
        if (ROOT / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, source / name)
    command = [
        sys.executable,
        "-m",
        "build",
        "--wheel",
        "--no-isolation",
        "--outdir",
        str(folder / "dist"),
        str(source),
    ]
    subprocess.run(command, capture_output=True, text=True, check=True, timeout=300)
    return next((folder / "dist").glob("enmi_torch-*.whl"))


def test_the_wheel_ships_the_configs_inside_the_package(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in (
        "fit_mask.yaml",
        "fit_mask_smoke.yaml",
        "paper_simulation.yaml",
        "paper_points.csv",
        "camera/paper.yaml",
    ):
        assert f"enmi_torch/configs/{name}" in names
    assert not any(name.startswith(("configs/", "tests/", "data_tools/", "train/")) for name in names)


def test_the_wheel_ships_the_example_pair(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    folder = ROOT / "enmi_torch" / "data" / "nanjing"
    bundled = sorted(path.name for path in folder.iterdir())
    assert bundled == ["nanjing.json", "nanjing_2000.png", "nanjing_2002.png", "nanjing_change.png"]
    assert {f"enmi_torch/data/nanjing/{name}" for name in bundled} <= names


@pytest.mark.slow
def test_the_installed_wheel_runs_its_commands_from_another_folder(wheel, tmp_path):
    """Installed (no clone on the path), the commands find their default configs in the package."""
    target = tmp_path / "site"
    install = [sys.executable, "-m", "pip", "install", "--no-deps", "--quiet", "--target", str(target), str(wheel)]
    subprocess.run(install, check=True, capture_output=True, timeout=300)
    environment = {**os.environ, "PYTHONPATH": str(target), "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    script = (
        "import sys, enmi_torch\n"
        "from enmi_torch.utils.resources import config_dir\n"
        "from enmi_torch.cli.reproduce_paper import main\n"
        "print(enmi_torch.__file__, config_dir())\n"
        "main(['--scores', '[nmi]', '--trials', '20', '--output-dir', 'paper'])\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, env=environment, capture_output=True, text=True, timeout=300
    )
    assert completed.returncode == 0, completed.stderr
    package, configs = completed.stdout.splitlines()[0].split()
    assert Path(package).is_relative_to(target) and Path(configs) == target / "enmi_torch" / "configs"
    assert (tmp_path / "paper" / "paper_simulation.png").is_file()


def test_the_top_level_imports_its_names_on_first_use():
    # import enmi_torch (and so every command's --help) does not import torch; each public name resolves when used.
    code = (
        "import sys, enmi_torch; assert 'torch' not in sys.modules, 'torch imported'; "
        "assert all(getattr(enmi_torch, name) is not None for name in enmi_torch.__all__); "
        "assert set(enmi_torch.__all__) <= set(dir(enmi_torch)); print(enmi_torch.ECR.__module__)"
    )
    completed = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert completed.returncode == 0, completed.stderr
    assert completed.stdout.strip() == "enmi_torch.scores.ecr"
    with pytest.raises(AttributeError, match="has no attribute 'not_a_name'"):
        enmi_torch.not_a_name  # noqa: B018
