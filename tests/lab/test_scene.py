"""What the harness checks when it loads a scene (`prdp_petsc.lab.training.scene`)."""

import pickle
import textwrap

import pytest

from prdp_petsc.lab.training.harness import build_scene
from prdp_petsc.lab.training.scene import Settings, check_presets, load_scene, preset_config

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
