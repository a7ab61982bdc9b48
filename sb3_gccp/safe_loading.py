"""Trained policies read from SB3 ``.zip`` files without running code from them.

An SB3 ``.zip`` holds the policy's weights (``policy.pth``, a plain state dict) and ``data``, a JSON map
in which classes, schedules and spaces are cloudpickle blobs that ``<Algorithm>.load`` unpickles: a file
from someone else can run any code there. sb3_gccp does not unpickle them. It rebuilds the policy from
its class and ``policy_kwargs`` on the spaces of the env it will drive, and reads the weights with
``torch.load(weights_only=True)``. Of ``data`` it reads JSON-plain fields only: the policy class's
module and name, ``policy_kwargs`` (the classes in it by their names), the shapes of the spaces the
policy was trained on, checked against the env's before it acts, and ``num_timesteps``. Classes are
imported from :data:`CLASS_PACKAGES` only, and must be of the kind the loading site takes.

``trusted=True`` (the CLI's ``--trust-pickle``) loads through ``<Algorithm>.load`` instead, which runs the
file's pickled code: for files one trusts whose policy cannot be rebuilt from plain data (for example a
``policy_kwargs`` value that is an object rather than a class, a number, a list or a map).

Files named by a model folder's own description (``hierarchy.yml``, ``baseline.yml``) must lie in that
folder (:func:`file_in_folder`), so that a downloaded folder cannot make sb3_gccp read or copy others.
"""

from __future__ import annotations

import importlib
import io
import json
import re
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

CLASS_PACKAGES = ("sb3_gccp", "stable_baselines3", "sb3_contrib", "torch")
"""Packages a class named in a model file's plain data may be imported from."""
KWARGS_CLASSES: dict[str, type] = {
    "features_extractor_class": BaseFeaturesExtractor,
    "activation_fn": nn.Module,
}
"""``policy_kwargs`` keys whose value is a class, with the base class it must derive from."""
UNUSED_KWARGS = ("optimizer_class", "optimizer_kwargs")
"""``policy_kwargs`` keys a policy that only acts does without (its optimiser never steps)."""
TRUST_HINT = "load it with --trust-pickle (trusted=True) only if you trust the file"
"""How messages point at the trusted path."""

Shapes = dict[str, tuple[tuple[int, ...], str]]
"""Shape and dtype of every array of a dict observation."""

_BOX = re.compile(r"'(\w+)': Box\([^()]*\(([\d, ]*)\), (\w+)\)")
"""One array of a dict space as SB3 records it: ``'bev': Box(0, 1, (1, 64, 64), uint8)``."""
_CLASS = re.compile(r"<class '([\w.]+)'>")
"""A class as SB3 records a ``policy_kwargs`` value it pickled."""
_INIT = re.compile(r"<function (\w+)\.__init__ at 0x[0-9a-f]+>")
"""The ``__init__`` SB3 records with a pickled class: the only plain field that names it."""


@dataclass(frozen=True)
class PolicyKind:
    """What a loading site takes: a name for messages and the algorithm that trains such policies."""

    name: str
    """For example ``motion-planner``."""
    algorithm: type[BaseAlgorithm]
    """Its trainer: its ``load`` is the trusted path, and its base policy bounds the recorded class."""

    @property
    def policy_base(self) -> type[BasePolicy]:
        """The class every policy of the algorithm derives from (the class of its ``MlpPolicy``)."""
        return self.algorithm.policy_aliases["MlpPolicy"]


@dataclass(frozen=True)
class SavedModel:
    """An SB3 ``.zip`` as sb3_gccp reads it: the JSON map of its ``data``, of which only plain fields are
    used, and the weights of ``policy.pth``."""

    path: Path
    data: Mapping[str, Any]

    @classmethod
    def read(cls, path: str | Path) -> SavedModel:
        """Open the file and read its ``data`` JSON (nothing is unpickled).

        :raises ValueError: one line, when the file is not a readable SB3 ``.zip``
        """
        path = Path(path)
        try:
            with zipfile.ZipFile(path) as archive:
                data = json.loads(archive.read("data"))
        except (zipfile.BadZipFile, zlib.error, EOFError, KeyError, ValueError) as err:
            raise ValueError(f"{path} is not a readable SB3 .zip: {first_line(err)}") from err
        if not isinstance(data, dict):
            raise ValueError(f"{path} is not a readable SB3 .zip: its data is not a map")
        return cls(path, data)

    @property
    def num_timesteps(self) -> int:
        """Environment steps the model was trained for."""
        steps = self.data.get("num_timesteps")
        if not isinstance(steps, int):
            raise ValueError(f"{self.path}: its data records no num_timesteps")
        return steps

    def policy_class(self, base: type[BasePolicy]) -> type[BasePolicy]:
        """The recorded policy class, imported by its module and name; it must derive from ``base``."""
        entry = self.data.get("policy_class")
        module = entry.get("__module__") if isinstance(entry, Mapping) else None
        init = _INIT.fullmatch(str(entry.get("__init__"))) if isinstance(entry, Mapping) else None
        if not isinstance(module, str) or init is None:
            raise ValueError(f"{self.path}: its data does not name its policy class; {TRUST_HINT}")
        return import_class(f"{module}.{init[1]}", base, f"{self.path}: policy class")

    def policy_kwargs(self) -> dict[str, Any]:
        """The recorded ``policy_kwargs`` from plain data (a class by its name), less the optimiser's."""
        entry = self.data.get("policy_kwargs") or {}
        if not isinstance(entry, Mapping):
            raise ValueError(f"{self.path}: its policy_kwargs are not a map")
        pickled = ":serialized:" in entry  # then values that were not plain data are their str()
        kwargs = {}
        for key, value in entry.items():
            if key.startswith(":") or key in UNUSED_KWARGS:
                continue
            if key in KWARGS_CLASSES and isinstance(value, str):
                named = _CLASS.fullmatch(value)
                if named is None:
                    raise ValueError(f"{self.path}: policy_kwargs.{key} is not a class: {value[:60]!r}")
                value = import_class(named[1], KWARGS_CLASSES[key], f"{self.path}: policy_kwargs.{key}")
            elif pickled and isinstance(value, str):
                raise ValueError(
                    f"{self.path}: policy_kwargs.{key} is an object, not plain data ({value[:60]!r}); "
                    + TRUST_HINT
                )
            kwargs[key] = value
        return kwargs

    def observation_shapes(self) -> Shapes:
        """Shape and dtype of every array of the dict observation the policy was trained on."""
        entry = self.data.get("observation_space")
        text = entry.get("spaces") if isinstance(entry, Mapping) else None
        shapes = {
            key: (tuple(int(n) for n in shape.replace(" ", "").split(",") if n), dtype)
            for key, shape, dtype in _BOX.findall(text if isinstance(text, str) else "")
        }
        if not shapes:
            raise ValueError(f"{self.path}: its data records no dict observation space; {TRUST_HINT}")
        return shapes

    def n_actions(self) -> int:
        """The number of discrete actions the policy was trained with."""
        entry = self.data.get("action_space")
        n = str(entry.get("n")) if isinstance(entry, Mapping) else ""
        if not isinstance(entry, Mapping) or "Discrete" not in str(entry.get(":type:")) or not n.isdigit():
            raise ValueError(f"{self.path}: its data records no discrete action space; {TRUST_HINT}")
        return int(n)

    def weights(self) -> dict[str, th.Tensor]:
        """The policy's state dict, read with ``torch.load(weights_only=True)``."""
        try:
            with zipfile.ZipFile(self.path) as archive:
                raw = archive.read("policy.pth")
            weights = th.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
        except Exception as err:  # a damaged file: zipfile, zlib, torch and its unpickler raise many kinds
            raise ValueError(f"{self.path}: cannot read its weights (policy.pth): {first_line(err)}") from err
        if not isinstance(weights, dict):
            raise ValueError(f"{self.path}: its policy.pth is not a state dict")
        return weights

    def policy(
        self, kind: PolicyKind, observation_space: spaces.Space, action_space: spaces.Space
    ) -> BasePolicy:
        """The policy rebuilt on an env's spaces, which are checked first, with the file's weights."""
        check_spaces(
            self.path, kind, self.observation_shapes(), self.n_actions(), observation_space, action_space
        )
        policy_class = self.policy_class(kind.policy_base)
        try:
            policy = policy_class(
                observation_space,
                action_space,
                _no_learning,
                optimizer_class=ActingOnly,
                **self.policy_kwargs(),
            )
        except (TypeError, ValueError, KeyError) as err:
            raise ValueError(
                f"{self.path}: cannot rebuild its {policy_class.__name__}: {first_line(err)}"
            ) from err
        weights = self.weights()
        misfit = _misfit(policy.state_dict(), weights)
        if misfit:
            raise ValueError(
                f"{self.path}: its weights do not fit a {kind.name} ({policy_class.__name__}): {misfit}"
            )
        policy.load_state_dict(weights)
        policy.set_training_mode(False)
        return policy


def load_policy(
    path: str | Path,
    kind: PolicyKind,
    observation_space: spaces.Space,
    action_space: spaces.Space,
    trusted: bool = False,
) -> BasePolicy:
    """A trained policy for an env of these spaces, checked against them before it acts.

    :param path: the SB3 ``.zip``
    :param kind: what the caller takes (motion-planner, decision-maker, a baseline)
    :param trusted: load through ``kind.algorithm.load``, which runs code pickled in the file
    :raises ValueError: one line, when the file cannot be read, is of another kind or does not fit the
        spaces
    """
    if not trusted:
        return SavedModel.read(path).policy(kind, observation_space, action_space)
    policy = kind.algorithm.load(path, device="cpu").policy
    if not isinstance(policy, kind.policy_base):
        raise ValueError(f"{path} is not a {kind.name}: its policy is a {type(policy).__name__}")
    trained_actions = policy.action_space.n if isinstance(policy.action_space, spaces.Discrete) else -1
    check_spaces(
        Path(path),
        kind,
        space_shapes(policy.observation_space),
        int(trained_actions),
        observation_space,
        action_space,
    )
    policy.set_training_mode(False)
    return policy


def check_spaces(
    path: Path,
    kind: PolicyKind,
    trained: Shapes,
    trained_actions: int,
    observation_space: spaces.Space,
    action_space: spaces.Space,
) -> None:
    """Raise ``ValueError`` (one line) unless a policy trained on ``trained`` observations and
    ``trained_actions`` actions fits an env of ``observation_space`` and ``action_space``."""
    given = space_shapes(observation_space)
    if set(trained) != set(given):
        raise ValueError(
            f"{path} is not a {kind.name} of this world: it observes {', '.join(sorted(trained))}; "
            f"a {kind.name} observes {', '.join(sorted(given))}"
        )
    for key in sorted(given):
        if trained[key] != given[key]:
            raise ValueError(
                f"{path} ({kind.name}) was trained on {key} of shape {_shape(trained[key])}, this world "
                f"gives {_shape(given[key])}: a world config key differs from its training"
            )
    n = action_space.n if isinstance(action_space, spaces.Discrete) else None
    if n is None or trained_actions != int(n):
        raise ValueError(
            f"{path} ({kind.name}) was trained with {trained_actions} actions, this world has {n}: a world "
            "config key differs from its training"
        )


def space_shapes(space: spaces.Space) -> Shapes:
    """Shape and dtype of every array of a dict space (none for another space)."""
    if not isinstance(space, spaces.Dict):
        return {}
    return {key: (tuple(sub.shape or ()), str(sub.dtype)) for key, sub in space.spaces.items()}


def import_class(dotted: str, base: type, what: str) -> type:
    """A class named by a model file, imported from :data:`CLASS_PACKAGES` only; it must derive from
    ``base``.

    :param what: how messages name the entry
    """
    if dotted.split(".")[0] not in CLASS_PACKAGES:
        raise ValueError(f"{what} {dotted!r} is not from {', '.join(CLASS_PACKAGES)}; {TRUST_HINT}")
    module_name, _, name = dotted.rpartition(".")
    try:
        found = getattr(importlib.import_module(module_name), name)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"{what} {dotted!r} cannot be imported: {first_line(err)}") from err
    if not isinstance(found, type) or not issubclass(found, base):
        raise ValueError(f"{what} {dotted!r} is not a {base.__name__}")
    return found


def file_in_folder(folder: Path, name: str, where: str) -> Path:
    """``folder / name`` for a file name read from a model folder's description, which must lie inside it.

    :param where: how messages name the entry, e.g. ``pretrained/hierarchy.yml: decider``
    :raises ValueError: an absolute name, a ``..`` step, or a link leading out of the folder
    """
    relative = Path(name)
    if not relative.parts or relative.is_absolute() or ".." in relative.parts:
        raise ValueError(f"{where} must name a file inside {folder}, got {name!r}")
    path = folder / relative
    if not path.resolve().is_relative_to(folder.resolve()):
        raise ValueError(f"{where} leads out of {folder}: {name!r} links to {path.resolve()}")
    return path


def first_line(err: BaseException) -> str:
    """An exception's message on one line (its first), for one-line error reports."""
    lines = str(err).strip().splitlines()
    return lines[0] if lines else type(err).__name__


class ActingOnly:
    """The optimiser of a policy rebuilt only to act: it holds no state and never steps.

    torch's own optimisers import ``torch._dynamo`` when the first one is made, about 3 s of every process
    that would load a policy only to act with it (``evaluate``, each decider-stage env worker).
    """

    def __init__(self, params: Any, **kwargs: Any) -> None:
        self.param_groups: list[dict[str, Any]] = []

    def step(self, closure: Any = None) -> None:
        """Refuse to train: the policy was rebuilt to act."""
        raise RuntimeError("a policy rebuilt by sb3_gccp.safe_loading only acts; load it with SB3 to train")

    def zero_grad(self, set_to_none: bool = True) -> None:
        """Nothing to clear."""


def _no_learning(progress_remaining: float) -> float:
    """The learning rate of a rebuilt policy's optimiser, which never steps."""
    return 0.0


def _shape(entry: tuple[tuple[int, ...], str]) -> str:
    shape, dtype = entry
    return f"{shape} {dtype}"


def _misfit(expected: Mapping[str, th.Tensor], weights: Mapping[str, Any]) -> str:
    """The first difference between a policy's state dict and weights read from a file ('' if none)."""
    missing = sorted(set(expected) - set(weights))
    unexpected = sorted(set(weights) - set(expected))
    if missing or unexpected:
        return (
            f"{len(missing)} missing ({', '.join(missing[:2])}), "
            f"{len(unexpected)} unexpected ({', '.join(unexpected[:2])})"
        )
    for key, tensor in expected.items():
        found = weights[key]
        if not isinstance(found, th.Tensor) or found.shape != tensor.shape:
            shape = tuple(found.shape) if isinstance(found, th.Tensor) else type(found).__name__
            return f"{key} is {shape} in the file, {tuple(tensor.shape)} here"
    return ""
