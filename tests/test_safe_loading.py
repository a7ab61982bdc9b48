"""Loading SB3 ``.zip`` files without unpickling: the shipped models as SB3 loads them, and what a
model file may not name."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch as th
from helpers import TINY_WORLD, rewrite_zip_data, save_tiny_models
from sb3_contrib import MaskablePPO

from gccp_envs.config import IntersectionConfig
from sb3_gccp.frozen import load_decider, load_planner
from sb3_gccp.hierarchy import load_hierarchy
from sb3_gccp.safe_loading import ActingOnly
from sb3_gccp.training.baselines import baseline_algorithm, load_baseline, read_baseline_spec

PRETRAINED = Path(__file__).resolve().parents[1] / "pretrained"
HIERARCHIES = sorted(path.parent for path in PRETRAINED.rglob("hierarchy.yml"))
BASELINES = sorted(path.parent for path in PRETRAINED.rglob("baseline.yml"))


def assert_same_policy(loaded: th.nn.Module, reference: th.nn.Module) -> None:
    assert type(loaded) is type(reference)
    ours, theirs = loaded.state_dict(), reference.state_dict()
    assert ours.keys() == theirs.keys() and all(th.equal(ours[key], theirs[key]) for key in ours)


@pytest.mark.parametrize("folder", HIERARCHIES, ids=lambda p: str(p.relative_to(PRETRAINED)) or "pretrained")
def test_every_shipped_hierarchy_loads_the_policies_sb3_loads(folder):
    hierarchy = load_hierarchy(folder)
    env = hierarchy.make_env()
    decider = hierarchy.decider_policy(env.config)
    assert_same_policy(decider.policy, MaskablePPO.load(hierarchy.decider, device="cpu").policy)
    if hierarchy.planner is not None:
        assert_same_policy(env.planner.policy, MaskablePPO.load(hierarchy.planner, device="cpu").policy)


@pytest.mark.parametrize("folder", BASELINES, ids=lambda p: p.name)
def test_every_shipped_baseline_acts_as_sb3s_load_does(folder):
    env, policy, name = load_baseline(folder)
    _, masked, _ = read_baseline_spec(folder)
    model = baseline_algorithm(name, masked).load(folder / "model.zip", device="cpu")
    obs, _ = env.reset(seed=0)
    for _ in range(10):
        masks = env.unwrapped.action_masks()
        extra = {"action_masks": masks} if isinstance(model, MaskablePPO) else {}
        action, _ = model.predict(obs, deterministic=True, **extra)
        assert policy(obs, masks) == int(action)
        obs, *_ = env.step(int(action))


@pytest.fixture(scope="module")
def tiny_planner(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_tiny_models(tmp_path_factory.mktemp("models"))[1]


def test_a_trusted_load_gives_the_same_policy(tiny_planner):
    world = IntersectionConfig.from_dict(TINY_WORLD)
    assert_same_policy(
        load_planner(tiny_planner, world).policy, load_planner(tiny_planner, world, True).policy
    )


def test_a_rebuilt_policy_has_an_optimiser_that_refuses_to_step(tiny_planner):
    """Rebuilt to act, a policy makes no torch optimiser (the first one made imports torch._dynamo)."""
    policy = load_planner(tiny_planner, IntersectionConfig.from_dict(TINY_WORLD)).policy
    assert isinstance(policy.optimizer, ActingOnly) and not policy.optimizer.param_groups
    policy.optimizer.zero_grad()
    with pytest.raises(RuntimeError, match="only acts"):
        policy.optimizer.step()


@pytest.mark.parametrize(
    ("policy_kwargs", "message"),
    [
        ({"activation_fn": "<class 'subprocess.Popen'>"}, "'subprocess.Popen' is not from sb3_gccp"),
        ({"activation_fn": "<class 'torch.optim.adam.Adam'>"}, "'torch.optim.adam.Adam' is not a Module"),
        ({"features_extractor_kwargs": "{'encoder': <object at 0x1>}"}, "is an object, not plain data"),
    ],
)
def test_a_class_or_object_a_model_file_names_in_its_policy_kwargs_is_refused(
    tiny_planner, tmp_path, policy_kwargs, message
):
    path = Path(shutil.copy(tiny_planner, tmp_path))
    rewrite_zip_data(path, policy_kwargs={":type:": "<class 'dict'>", ":serialized:": "", **policy_kwargs})
    with pytest.raises(ValueError, match=message) as raised:
        load_planner(path, IntersectionConfig.from_dict(TINY_WORLD))
    assert "\n" not in str(raised.value)


def test_a_policy_class_of_another_algorithm_is_refused(tiny_planner, tmp_path):
    path = Path(shutil.copy(tiny_planner, tmp_path))
    init = "<function MultiInputPolicy.__init__ at 0x7f0000000000>"
    rewrite_zip_data(path, policy_class={"__module__": "stable_baselines3.dqn.policies", "__init__": init})
    with pytest.raises(ValueError) as raised:
        load_planner(path, IntersectionConfig.from_dict(TINY_WORLD))
    assert "'stable_baselines3.dqn.policies.MultiInputPolicy' is not a MaskableActorCriticPolicy" in str(
        raised.value
    )


def test_a_decider_loads_where_a_planner_does_not(tiny_planner):
    world = IntersectionConfig.from_dict(TINY_WORLD)
    decider = load_decider(tiny_planner.parent / "decider.zip", world, deterministic=False)
    assert not decider.deterministic
    with pytest.raises(ValueError) as raised:
        load_decider(tiny_planner, world)
    assert "planner.zip is not a decision-maker of this world: it observes bev, goal," in str(raised.value)
