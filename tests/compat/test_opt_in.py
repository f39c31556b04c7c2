"""The plugin is opt-in: importing it registers the env, the policy and its processor step and
changes nothing else of LeRobot, and a LeRobot dataset of another project reads exactly as with stock
LeRobot, bit for bit, even once our fast reads are switched on."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


# One fresh interpreter for the two tests below (an interpreter that imports LeRobot costs seconds):
# it notes LeRobot's functions, imports the plugin as LeRobot's CLIs do, then builds another project's
# configs and one of ours, and prints what it saw after each step.
PROBE = """
import json, os, sys
os.environ["HF_HUB_OFFLINE"] = "1"
import lerobot.scripts.lerobot_eval as lerobot_eval
import lerobot.envs.factory as env_factory
from draccus.utils import DecodingError
from lerobot.configs.default import DatasetConfig
from lerobot.configs.eval import EvalPipelineConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.datasets.dataset_reader import DatasetReader

def functions():
    return {
        "DatasetConfig.__post_init__": DatasetConfig.__post_init__,
        "TrainPipelineConfig.validate": TrainPipelineConfig.validate,
        "EvalPipelineConfig.__post_init__": EvalPipelineConfig.__post_init__,
        "DecodingError.__str__": DecodingError.__str__,
        "sys.excepthook": sys.excepthook,
        "make_env_pre_post_processors": env_factory.make_env_pre_post_processors,
    }

before = (DatasetReader.get_item, DatasetReader._query_hf_dataset, lerobot_eval.rollout)
stock = functions()
env = dict(os.environ)
import lerobot_env_formation  # noqa: F401  (what LeRobot's CLIs import: the plugin)
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs.configs import EnvConfig
from lerobot.processor import ProcessorStepRegistry
after = (DatasetReader.get_item, DatasetReader._query_hf_dataset, lerobot_eval.rollout)
imported = {
    "same": [a is b for a, b in zip(before, after)],
    "getstate": "__getstate__" in vars(DatasetReader),
    "env": dict(os.environ) == env,
    "policy": "formation_diffusion" in PreTrainedConfig.get_known_choices(),
    "env_config": "formation" in EnvConfig.get_known_choices(),
    "step": "formation_egocentric_obstacles" in ProcessorStepRegistry.list(),
    "patched": [k for k, f in functions().items() if f is not stock[k]],
}
from lerobot.envs.configs import PushtEnv
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
dataset = DatasetConfig(repo_id="other/arm", root=sys.argv[1])
train = TrainPipelineConfig(dataset=dataset, env=PushtEnv(), policy=DiffusionConfig(device="cpu"))
others = [k for k, f in functions().items() if f is not stock[k]]
from lerobot_formation.envs.env_config import FormationEnvConfig
FormationEnvConfig()
ours = [k for k, f in functions().items() if f is not stock[k]]
print(json.dumps({"imported": imported, "others": others, "ours": ours}))
"""


@pytest.fixture(scope="module")
def probe(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("opt_in")
    out = subprocess.run(
        [sys.executable, "-c", PROBE, str(tmp / "missing")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_the_plugin_registers_and_patches_nothing(probe):
    assert probe["imported"] == {
        "same": [True, True, True],
        "getstate": False,
        "env": True,
        "policy": True,
        "env_config": True,
        "step": True,
        "patched": [],
    }


def test_other_projects_configs_leave_lerobot_untouched_ours_switch_the_run_checks_on(probe):
    """Importing the plugin and building another project's configs (even a dataset root that does
    not exist, offline) changes none of the LeRobot functions our run checks wrap; building one of
    our configs wraps only lerobot-train's and lerobot-eval's pipeline configs."""
    assert probe["others"] == []
    assert probe["ours"] == [
        "TrainPipelineConfig.validate",
        "EvalPipelineConfig.__post_init__",
        "DecodingError.__str__",
        "sys.excepthook",
    ]


WRITE_AND_READ = """
import sys, torch
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

root, mode = sys.argv[1], sys.argv[2]
if mode == "write":  # another project's dataset, written with LeRobot's own writer, then read stock
    features = {
        "observation.joints": {"dtype": "float32", "shape": (6,), "names": None},
        "observation.gripper": {"dtype": "float32", "shape": (1,), "names": None},
        "action": {"dtype": "float32", "shape": (3,), "names": None},
        "phase": {"dtype": "int64", "shape": (1,), "names": None},
    }
    ds = LeRobotDataset.create("other/arm", fps=15, root=root, features=features, use_videos=False)
    rng = np.random.default_rng(0)
    for ep in range(3):
        for t in range(12 + 5 * ep):
            ds.add_frame({
                "observation.joints": rng.normal(size=6).astype(np.float32),
                "observation.gripper": rng.uniform(size=1).astype(np.float32),
                "action": rng.normal(size=3).astype(np.float32),
                "phase": np.array([t % 4], dtype=np.int64),
                "task": f"pick {ep % 2}",
            })
        ds.save_episode()
    ds.finalize()
if mode == "plugin":  # our plugin imported and our fast reads switched on, as in a formation run
    import lerobot_env_formation  # noqa: F401
    from lerobot_formation.compat import fast_reads
    assert fast_reads.install()
delta = {"observation.joints": [-2 / 15, -1 / 15, 0.0], "action": [k / 15 for k in range(5)]}
items = {}
for name, kw in {"windows": {"delta_timestamps": delta}, "plain": {}, "some": {"episodes": [0, 2]}}.items():
    ds = LeRobotDataset("other/arm", root=root, **kw)
    items[name] = [ds[i] for i in range(len(ds))]
torch.save(items, sys.argv[3])
"""


def test_another_projects_dataset_reads_as_with_stock_lerobot(tmp_path, monkeypatch):
    """Stock: written and read in a fresh interpreter that never imports the plugin; ours: read in
    this process (the plugin imported, as in every test here) with the fast reads switched on."""
    from lerobot.datasets.dataset_reader import DatasetReader

    from lerobot_formation.compat import fast_reads

    script = tmp_path / "rw.py"
    script.write_text(WRITE_AND_READ)
    root = tmp_path / "other_arm"
    out = subprocess.run(
        [sys.executable, str(script), str(root), "write", str(tmp_path / "stock.pt")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    was_fast = DatasetReader.get_item.__name__ == "_fast_get_item"
    monkeypatch.setattr(sys, "argv", [str(script), str(root), "plugin", str(tmp_path / "plugin.pt")])
    try:
        exec(compile(WRITE_AND_READ, str(script), "exec"), {"__name__": "rw"})
    finally:
        if not was_fast:
            fast_reads.uninstall()
    stock = torch.load(tmp_path / "stock.pt", weights_only=False)
    ours = torch.load(tmp_path / "plugin.pt", weights_only=False)
    assert stock.keys() == ours.keys() and len(stock["windows"]) == 12 + 17 + 22
    for name in stock:
        assert len(stock[name]) == len(ours[name]) > 0
        for a, b in zip(stock[name], ours[name], strict=True):
            assert a.keys() == b.keys()
            for k in a:
                if isinstance(a[k], torch.Tensor):
                    assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), (name, k)
                else:
                    assert a[k] == b[k], (name, k)
    assert stock["windows"][0]["action"].shape == (5, 3)  # not vacuous: windows were read
