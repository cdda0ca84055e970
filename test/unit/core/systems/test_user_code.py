"""User code next to the system file (saml_ros.user_code, issue 27 item 4).

``base_model: {function: "dynamics:f_hat"}`` imports ``dynamics.py`` from the system file's folder (or the folders
``base_model.path`` names, relative to the file), with no ``PYTHONPATH``; the definition stores the folder
absolute, so a checkpoint finds the module from any working directory. The end-to-end test runs the learner as a
real process from another working directory, with a robot folder of its own in a temporary directory, and then
``bag_info``, ``load_model`` and ``export`` as fresh processes with only saml_ros itself on ``PYTHONPATH``.
"""

from __future__ import annotations

import os
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers.your_robot import f_hat_np, robot_folder

from saml_ros.systems.system_file import SystemFileError

pytestmark = pytest.mark.usefixtures("restore_registry")  # loading a system file registers its robot by name


# ------------------------------------------------------------------------------------------ in process
def test_module_next_to_the_system_file_is_found_and_recorded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    from saml_ros.user_code import UserFunction, load_system_file

    path = robot_folder(tmp_path, module="ucp_dyn_a", constants="ucp_const_a")
    monkeypatch.chdir(tmp_path.parent)  # not the robot's folder
    system = load_system_file(os.path.relpath(path))
    base = system.definition["base_model"]
    assert base["path"] == [str(path.parent.resolve())]  # recorded absolute: a checkpoint finds it anywhere
    assert isinstance(system.user_function, UserFunction)
    x, u = system.sample_inputs(8, np.random.default_rng(0))
    np.testing.assert_allclose(system.base_step_np(x, u), f_hat_np(x, u, system.dt), atol=1e-6)
    # it pickles as its name and folder (how it reaches the learner's training process)
    again = pickle.loads(pickle.dumps(system.user_function))
    assert again.target == "ucp_dyn_a:f_hat" and again.search == (str(path.parent.resolve()),)


def test_path_key_names_a_folder_relative_to_the_file(tmp_path: Path) -> None:
    from saml_ros.user_code import load_system_file

    path = robot_folder(tmp_path, module="ucp_dyn_b", constants="ucp_const_b", sub="models",
                        base_model={"function": "ucp_dyn_b:f_hat", "path": "models"})
    system = load_system_file(path)
    assert system.definition["base_model"]["path"] == [str((path.parent / "models").resolve())]
    x, u = system.sample_inputs(4, np.random.default_rng(1))
    np.testing.assert_allclose(system.base_step_np(x, u), f_hat_np(x, u, system.dt), atol=1e-6)


def test_missing_module_names_the_file_and_where_it_looked(tmp_path: Path) -> None:
    from saml_ros.user_code import load_system_file, system_from_definition

    path = robot_folder(tmp_path, module="ucp_dyn_c", constants="ucp_const_c")
    (path.parent / "ucp_dyn_c.py").unlink()
    with pytest.raises(SystemFileError, match=r"base model function 'ucp_dyn_c:f_hat': no module 'ucp_dyn_c' "
                                              r"\(ucp_dyn_c.py or a package ucp_dyn_c/\) in .*my_robot \(the system "
                                              r"file's folder, or base_model.path\), nor on the Python path"):
        load_system_file(path)
    # a definition stored by a checkpoint whose robot folder has moved away
    path = robot_folder(tmp_path / "two", module="ucp_dyn_d", constants="ucp_const_d")
    definition = load_system_file(path).params()["definition"]
    shutil.move(str(path.parent), str(tmp_path / "moved"))
    sys.modules.pop("ucp_dyn_d", None)
    with pytest.raises(SystemFileError, match=r"no module 'ucp_dyn_d' .* in .*my_robot \(no such folder\)"):
        system_from_definition(definition)


def test_two_robots_with_modules_of_one_name_are_refused_clearly(tmp_path: Path) -> None:
    from saml_ros.user_code import load_system_file

    first = robot_folder(tmp_path / "a", module="ucp_dyn_e", constants="ucp_const_e")
    load_system_file(first)
    second = robot_folder(tmp_path / "b", module="ucp_dyn_e", constants="ucp_const_e2")
    raw = yaml.safe_load(second.read_text())
    raw["name"] = "other_robot"
    second.write_text(yaml.safe_dump(raw))
    with pytest.raises(SystemFileError, match=r"a module 'ucp_dyn_e' is already imported in this process from "
                                              r".*a/my_robot, not from .*b/my_robot"):
        load_system_file(second)


def test_path_only_for_functions() -> None:
    from saml_ros.core.dynamics.base_models import BaseModelError, BaseModelSpec

    with pytest.raises(BaseModelError, match="only a 'function' base model"):
        BaseModelSpec.parse({"builtin": "hold", "path": "."})
    with pytest.raises(BaseModelError, match="expected a directory or a list"):
        BaseModelSpec.parse({"function": "a:b", "path": [3]})
