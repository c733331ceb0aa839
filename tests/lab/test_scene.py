"""What the harness checks when it loads a scene (`prdp_petsc.lab.training.scene`)."""

import pickle
import re
import shlex
import textwrap
from pathlib import Path

import pytest

from prdp_petsc.lab.training.harness import build_scene
from prdp_petsc.lab.training.scene import (
    Settings,
    check_presets,
    load_scene,
    merged_scene,
    preset_config,
)

ROOT = Path(__file__).resolve().parents[2]

SCENE = """
import numpy as np, scipy.sparse as sp, torch
import prdp_petsc as pp
from prdp_petsc.fem.fd import laplacian
from prdp_petsc import lab

PRESETS = {presets}

def build(config, seed):
    A = (sp.identity(6) - 1e-2 * laplacian(6)).tocsr()
    solver = pp.KSPSolver({{"ksp_type": "cg", "pc_type": "none"}}, prefix="sc_", max_it=1)
    theta = torch.ones(6, dtype=torch.float64, requires_grad=True)
    return lab.Scene(
        solvers=[solver], optimizer=torch.optim.SGD([theta], lr=config["lr"]),
        batches=lambda e, g: [None], loss=lambda _: pp.solve(A, theta, solver).sum(),
        validate=lambda: 0.0, probe=lambda: (A, np.ones(6), None), epochs=config["epochs"],
    )
"""


def scene_file(tmp_path, presets: str, name: str = "scene"):
    path = tmp_path / f"{name}.py"
    path.write_text(SCENE.format(presets=textwrap.dedent(presets)))
    return path


def test_presets_with_the_same_keys_load_and_build(tmp_path):
    path = scene_file(
        tmp_path, '{"quick": {"lr": 0.1, "epochs": 2}, "paper": {"epochs": 9, "lr": 1.0}}'
    )
    module = load_scene(path)
    assert build_scene(module, "paper", 0).epochs == 9


def test_a_preset_that_lacks_a_key_is_refused_at_load(tmp_path):
    path = scene_file(
        tmp_path, '{"quick": {"lr": 0.1, "epochs": 2}, "paper": {"lr": 1.0}}', "lacks"
    )
    with pytest.raises(ValueError, match=r"preset 'paper' lacks the setting 'epochs'.*'quick'"):
        load_scene(path)


def test_a_preset_with_an_unknown_key_is_refused_at_load(tmp_path):
    presets = '{"quick": {"lr": 0.1, "epochs": 2}, "paper": {"lr": 1.0, "epochs": 2, "lrr": 3}}'
    path = scene_file(tmp_path, presets, "unknown")
    with pytest.raises(ValueError, match=r"preset 'paper' names the setting 'lrr'.*'quick'"):
        load_scene(path)


@pytest.mark.parametrize(
    "presets, message",
    [
        ("{}", "non-empty dict"),
        ("[]", "non-empty dict"),
        ('{"quick": [1]}', r"PRESETS\['quick'\] must be a dict"),
        ('{"quick": {1: 2}}', "identifiers"),
    ],
)
def test_presets_that_are_not_dicts_of_settings_are_refused(tmp_path, presets, message):
    with pytest.raises(TypeError, match=message):
        load_scene(scene_file(tmp_path, presets, f"bad{abs(hash(presets))}"))


def test_a_module_given_directly_is_checked_too():
    class Wrapper:  # what the harness takes as module= (tests wrap build this way)
        PRESETS = {"quick": {"a": 1}, "paper": {"b": 2}}

    with pytest.raises(ValueError, match="lacks the setting 'a'"):
        check_presets(Wrapper)
    with pytest.raises(ValueError, match="lacks the setting 'a'"):
        preset_config(Wrapper, "quick")


def test_build_reading_a_setting_no_preset_names_fails_naming_key_and_preset(tmp_path):
    path = scene_file(tmp_path, '{"quick": {"lr": 0.1}}', "reads")  # build reads "epochs"
    module = load_scene(path)
    with pytest.raises(KeyError, match=r"'epochs' is not in preset 'quick' of scene reads.py"):
        build_scene(module, "quick", 0)


def test_settings_are_a_dict_that_pickles_with_its_names():
    config = Settings({"a": 1}, scene="s.py", preset="quick a=1")
    assert config == {"a": 1} and isinstance(config, dict)
    again = pickle.loads(pickle.dumps(config))
    assert again == config and (again.scene, again.preset) == ("s.py", "quick a=1")
    with pytest.raises(KeyError, match="preset 'quick a=1'"):
        again["b"]
    assert again.get("b", 2) == 2


def test_a_scene_file_merged_into_another_is_named_as_it_is_now():
    assert merged_scene("demos/heat2d.py", "paper_mlp") == ("demos/heat.py", "paper_mlp")
    assert merged_scene("/x/demos/heat3d.py", "paper k_step=5") == (
        "/x/demos/heat.py",
        "paper3d k_step=5",
    )
    assert merged_scene("demos/ns2d.py", "paper") == ("demos/ns2d.py", "paper")


def test_the_results_pages_regenerate_with_scene_files_and_presets_that_exist():
    """A run recorded under demos/heat2d.py or heat3d.py is regenerated (and an earlier
    experiment run) by demos/heat.py's name and presets: every scene file a page tells
    to run exists and has the preset it names."""
    from prdp_petsc.lab.reports import pages

    written = pages.pages(ROOT / "docs" / "data", ROOT / "docs" / "images")
    commands = [
        line
        for text in written.values()
        for line in re.findall(r"Regenerate: `prdp-petsc pages record \S+ -- ([^`]*)`", text)
    ]
    earlier = written["index.md"].split("| experiment")[1]
    commands += re.findall(r"`prdp-petsc ([^`]*)`", earlier)
    scenes = {}
    for command in commands:
        argv = shlex.split(command)
        for i, arg in enumerate(argv):
            if arg.endswith(".py"):
                assert (ROOT / arg).is_file(), command
                module = scenes.setdefault(arg, load_scene(ROOT / arg))
                if "--preset" in argv[i:]:
                    preset = argv[argv.index("--preset", i) + 1].split()[0]
                    assert preset in module.PRESETS, command
    assert any("demos/heat.py --preset paper3d" in c for c in commands)
