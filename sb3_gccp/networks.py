"""The paper's shared scene encoder (III-C-1), built to be cheap on a CPU.

The structure is the paper's: a shared self-attention history encoder turns each vehicle's T_h
history vectors into one L-dim feature f_h; self-attention over the vehicle nodes gives the
interaction feature; a shared route encoder turns each route's N_p vectors into one L-dim feature;
cross-attention from each vehicle (query: its interaction feature) to its N_r route features gives
the route attention feature; a CNN encodes the bird's-eye view of the drivable area and a 2-layer
MLP the goal pose (x, y, heading). Per vehicle the five L-dim features are concatenated into 5L.

Where the paper is silent, these choices keep a training step cheap (MaskablePPO with 2 envs must
train faster than stock PPO on highway-env's intersection; see ``benchmarks/train_speed.py``):

- **Narrow tokens.** History and route vectors are embedded as ``token_size``-wide tokens (32, not
  L = 128) by a 2-layer MLP; only the pooled feature of a set is projected to L.
- **Attention pooling.** A set of tokens becomes one vector by multi-head attention from a learned
  query (the Set Transformer's pooling, Lee et al. 2019), computed as one linear layer per token.
  History tokens first pass one masked self-attention layer (residual, LayerNorm), as in the paper;
  route tokens skip it by default (``route_self_attention``): with 18 routes per scene it would
  cost more than the rest of the encoder.
- **Route patches.** ``route_patch`` consecutive route vectors (1 m apart) form one route token, so
  a 50-vector route is 10 tokens.
- **Only what is there.** Absent vehicles and absent routes are not encoded at all (in traffic a
  third of the route slots and two thirds of the vehicle slots are real).
- **Small CNN.** The 64x64 BEV is average-pooled by ``bev_pool`` (4: 3.1 m cells holding the
  drivable fraction), then 3x3 stride-2 convolutions bring it to 4x4 and a linear layer to L.
- **Fixed input scales.** Positions are divided by ``distance_scale`` and speeds by ``speed_scale``;
  headings (radians) and vehicle/route indices enter as they are.

Padding never leaks: padded vectors are zeroed before they are embedded, padded tokens, absent
vehicles and absent routes are masked out of every attention as keys, and the features of absent
vehicles (no history vector) and of vehicles without any route are zero. Masked keys get a large
finite negative score rather than -inf, so a query whose keys are all padded gets a finite output
(then zeroed) and finite gradients instead of NaN.

Consumers encode the scene once and combine it with many goals: :meth:`SceneEncoder.encode` gives a
:class:`SceneFeatures`, :meth:`SceneEncoder.goal_features` the goal features, and
:meth:`SceneEncoder.vehicle_features` / :meth:`SceneEncoder.ego_features` the concatenated 5L
features for every (goal, vehicle) pair or for the ego.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch as th
import torch.nn.functional as F
from torch import nn

from gccp_envs.config import IntersectionConfig, reject_unknown_keys, require_int
from gccp_envs.observation import HISTORY_FEATURES, ROUTE_FEATURES

HISTORY_LAYOUT = ("distance", "distance", "angle", "speed") * 2 + ("index",)
"""Kind of each history feature: [x, y, heading, speed] at j-1 and at j, vehicle index i."""
ROUTE_LAYOUT = ("distance", "distance", "angle") * 2 + ("index", "index")
"""Kind of each route feature: [x, y, heading] at k and at k+1, vehicle index i, route index j."""
GOAL_LAYOUT = ("distance", "distance", "angle")
"""Kind of each goal feature: x, y, heading in the ego frame."""

_MASKED_SCORE = -1e9
"""Attention score of a padded key: its softmax weight is exactly 0 next to any real key."""


@dataclass(frozen=True)
class EncoderConfig:
    """Sizes of the scene encoder; the paper sets only L (III-C-1), the rest are ours (module docstring)."""

    hidden_size: int = 128
    """L: width of every per-vehicle feature, of the BEV feature and of the goal feature (paper: 128)."""
    num_heads: int = 4
    """Attention heads of the vehicle self-attention and of the vehicle-to-route cross-attention."""
    token_size: int = 32
    """Width of the history and route tokens inside their set encoders (narrower than L for speed)."""
    token_heads: int = 2
    """Attention heads inside the history and route set encoders."""
    history_self_attention: bool = True
    """Pass the history tokens through a self-attention layer before pooling them (paper)."""
    route_self_attention: bool = False
    """Pass the route tokens through a self-attention layer before pooling them (paper; slow)."""
    history_patch: int = 1
    """Consecutive history vectors embedded together as one history token."""
    route_patch: int = 5
    """Consecutive route vectors embedded together as one route token (50 vectors -> 10 tokens)."""
    bev_pool: int = 4
    """Average-pooling factor applied to the BEV first (64x64 -> 16x16 cells of drivable fraction)."""
    bev_channels: tuple[int, ...] = (16, 32)
    """Output channels of the BEV CNN's 3x3 stride-2 convolutions (16x16 -> 4x4 with two)."""
    distance_scale: float = 20.0
    """Metres per unit of every position fed to the networks."""
    speed_scale: float = 10.0
    """Metres per second per unit of every speed fed to the networks."""

    def __post_init__(self) -> None:
        positive = ("hidden_size", "num_heads", "token_size", "token_heads", "history_patch", "route_patch")
        for name in (*positive, "bev_pool"):
            require_int(name, getattr(self, name))
        if self.hidden_size % self.num_heads:
            raise ValueError(
                f"hidden_size {self.hidden_size} is not a multiple of num_heads {self.num_heads}"
            )
        if self.token_size % self.token_heads:
            raise ValueError(
                f"token_size {self.token_size} is not a multiple of token_heads {self.token_heads}"
            )
        if not self.bev_channels or any(c < 1 for c in self.bev_channels):
            raise ValueError(f"bev_channels must be positive channel counts, got {self.bev_channels!r}")
        if self.distance_scale <= 0 or self.speed_scale <= 0:
            raise ValueError("distance_scale and speed_scale must be positive")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any] | None = None) -> EncoderConfig:
        """Build a config from a mapping (for example a YAML map), rejecting unknown keys by name.

        :param values: field values; missing fields keep their defaults
        :return: the validated config
        """
        if values is not None and not isinstance(values, Mapping):
            raise ValueError(f"the encoder config is a map of its keys, got {values!r}")
        values = dict(values or {})
        reject_unknown_keys(values, cls, "encoder config")
        if isinstance(values.get("bev_channels"), list):
            values["bev_channels"] = tuple(values["bev_channels"])
        return cls(**values)

    def input_scale(self, layout: tuple[str, ...]) -> th.Tensor:
        """Factors that bring each feature of ``layout`` to unit scale.

        :param layout: kind of each feature: 'distance', 'speed', 'angle' or 'index'
        :return: (len(layout),) float tensor
        """
        per_kind = {
            "distance": 1 / self.distance_scale,
            "speed": 1 / self.speed_scale,
            "angle": 1,
            "index": 1,
        }
        return th.tensor([per_kind[kind] for kind in layout], dtype=th.float32)


class SceneFeatures(NamedTuple):
    """Goal-independent features of a batch of scenes (B scenes, V vehicles, hidden size L)."""

    history: th.Tensor
    """(B, V, L) history features f_h (zero for absent vehicles)."""
    interaction: th.Tensor
    """(B, V, L) interaction features (zero for absent vehicles)."""
    route: th.Tensor
    """(B, V, L) route attention features (zero for absent vehicles and vehicles without routes)."""
    drivable: th.Tensor
    """(B, L) drivable-area feature f_d."""
    present: th.Tensor
    """(B, V) bool: the vehicle has at least one history vector (vehicle 0 is the ego)."""


class MaskedAttention(nn.Module):
    """Multi-head scaled dot-product attention (Vaswani et al. 2017) in which padded keys get no weight.

    One query per set is computed by broadcasting products (thousands of tiny sets, where that beats
    batched matrix products); several queries per set by torch's fused attention.

    :param query_size: width of the queries
    :param key_size: width of the keys (and values)
    :param embed_size: width of the attention and of its output
    :param num_heads: number of heads (divides ``embed_size``)
    """

    def __init__(self, query_size: int, key_size: int, embed_size: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads, self.head_size = num_heads, embed_size // num_heads
        self.scale = self.head_size**-0.5
        self.query = nn.Linear(query_size, embed_size)
        self.key_value = nn.Linear(key_size, 2 * embed_size)
        self.out = nn.Linear(embed_size, embed_size)

    def forward(self, queries: th.Tensor, keys: th.Tensor, key_mask: th.Tensor) -> th.Tensor:
        """Attend from every query to the real keys of its set.

        :param queries: (N, Q, query_size)
        :param keys: (N, K, key_size)
        :param key_mask: (N, K) bool, True for real keys
        :return: (N, Q, embed_size); finite but meaningless where a set has no real key
        """
        return self.attend(queries, self.key_value(keys), key_mask)

    def attend(self, queries: th.Tensor, key_value: th.Tensor, key_mask: th.Tensor) -> th.Tensor:
        """:meth:`forward` with the keys already projected by :attr:`key_value` (only the real ones need be).

        :param queries: (N, Q, query_size)
        :param key_value: (N, K, 2 * embed_size) projected keys and values
        :param key_mask: (N, K) bool, True for real keys
        :return: (N, Q, embed_size)
        """
        n, num_queries, _ = queries.shape
        heads, size = self.num_heads, self.head_size
        key, value = key_value.view(n, key_value.shape[1], 2, heads, size).unbind(2)  # (N, K, H, d)
        if num_queries == 1:
            query = (self.query(queries) * self.scale).view(n, 1, heads, size)
            score = (query * key).sum(-1)  # (N, K, H)
            weight = score.masked_fill(~key_mask[..., None], _MASKED_SCORE).softmax(1)
            attended = (weight[..., None] * value).sum(1)  # (N, H, d)
        else:
            query = self.query(queries).view(n, num_queries, heads, size).transpose(1, 2)
            bias = th.zeros(key_mask.shape, dtype=query.dtype, device=query.device)
            bias = bias.masked_fill_(~key_mask, _MASKED_SCORE)[:, None, None, :]
            attended = F.scaled_dot_product_attention(
                query, key.transpose(1, 2), value.transpose(1, 2), attn_mask=bias
            ).transpose(1, 2)
        return self.out(attended.reshape(n, num_queries, heads * size))


class AttentionPool(nn.Module):
    """Multi-head attention from one learned query to a padded set of tokens (Set Transformer's PMA).

    With a fixed query, a head's score of a token, q_h . (W_k x + b_k)_h / sqrt(d_h), is linear in
    the token, so the scores and the values come from one linear layer.

    :param size: width of the tokens and of the pooled output
    :param num_heads: number of heads (divides ``size``)
    """

    def __init__(self, size: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.score_value = nn.Linear(size, num_heads + size)

    def forward(self, tokens: th.Tensor, mask: th.Tensor) -> th.Tensor:
        """Pool N sets of T tokens.

        :param tokens: (N, T, size)
        :param mask: (N, T) bool, True for real tokens
        :return: (N, size); finite but meaningless for a set without any real token
        """
        n, t, size = tokens.shape
        heads = self.num_heads
        score, value = self.score_value(tokens).split((heads, size), -1)
        weight = score.masked_fill(~mask[..., None], _MASKED_SCORE).softmax(1)  # (N, T, H)
        return (weight[..., None] * value.view(n, t, heads, size // heads)).sum(1).view(n, size)


class VectorSetEncoder(nn.Module):
    """Attention encoder of a padded set of vectors (a history or a route) into one feature.

    Vectors are scaled and zeroed where padded, grouped ``patch`` at a time with their mask bits into
    tokens, embedded by a 2-layer MLP, optionally passed through one masked self-attention layer
    (residual, LayerNorm), pooled by :class:`AttentionPool` and projected to ``out_size``.

    :param in_features: features per vector
    :param scale: (in_features,) factors applied to the vectors first
    :param patch: vectors per token
    :param token_size: width of the tokens
    :param num_heads: attention heads
    :param self_attention: whether tokens attend to each other before pooling
    :param out_size: width of the output feature
    """

    scale: th.Tensor

    def __init__(
        self,
        in_features: int,
        scale: th.Tensor,
        patch: int,
        token_size: int,
        num_heads: int,
        self_attention: bool,
        out_size: int,
    ) -> None:
        super().__init__()
        self.patch = patch
        self.register_buffer("scale", scale, persistent=False)
        self.embed = nn.Sequential(
            nn.Linear(patch * (in_features + 1), token_size),
            nn.ReLU(),
            nn.Linear(token_size, token_size),
            nn.ReLU(),
        )
        self.self_attention = (
            MaskedAttention(token_size, token_size, token_size, num_heads) if self_attention else None
        )
        self.norm = nn.LayerNorm(token_size) if self_attention else None
        self.pool = AttentionPool(token_size, num_heads)
        self.out = nn.Sequential(nn.Linear(token_size, out_size), nn.ReLU())

    def forward(self, vectors: th.Tensor, mask: th.Tensor) -> th.Tensor:
        """Encode N sets of P vectors.

        :param vectors: (N, P, in_features)
        :param mask: (N, P) float or bool, nonzero for real vectors
        :return: (N, out_size); finite but meaningless for a set without any real vector
        """
        n, points, _ = vectors.shape
        mask = mask.to(vectors.dtype)
        tokens = th.cat((vectors * self.scale * mask[..., None], mask[..., None]), -1)
        pad = -points % self.patch
        if pad:
            tokens = F.pad(tokens, (0, 0, 0, pad))
            mask = F.pad(mask, (0, pad))
        num_tokens = (points + pad) // self.patch
        tokens = tokens.view(n, num_tokens, self.patch * tokens.shape[-1])
        token_mask = mask.view(n, num_tokens, self.patch).amax(-1) > 0
        x = self.embed(tokens)
        if self.self_attention is not None and self.norm is not None:
            x = self.norm(x + self.self_attention(x, x, token_mask))
        return self.out(self.pool(x, token_mask))


class SceneEncoder(nn.Module):
    """The paper's feature encoder (III-C-1): per-vehicle history, interaction, route attention,
    drivable-area and goal features.

    :param config: sizes (default :class:`EncoderConfig`)
    :param history_features: features per history vector
    :param route_features: features per route vector
    :param bev_shape: (channels, height, width) of the bird's-eye view (default: the world's)
    """

    goal_scale: th.Tensor

    def __init__(
        self,
        config: EncoderConfig | None = None,
        history_features: int = HISTORY_FEATURES,
        route_features: int = ROUTE_FEATURES,
        bev_shape: tuple[int, int, int] | None = None,
    ) -> None:
        super().__init__()
        self.config = config = config or EncoderConfig()
        if (history_features, route_features) != (len(HISTORY_LAYOUT), len(ROUTE_LAYOUT)):
            raise ValueError(
                f"expected {len(HISTORY_LAYOUT)} history and {len(ROUTE_LAYOUT)} route features, "
                f"got {history_features} and {route_features}"
            )
        if bev_shape is None:
            size = IntersectionConfig().bev_size
            bev_shape = (1, size, size)
        hidden = config.hidden_size
        self.history_encoder = VectorSetEncoder(
            history_features,
            config.input_scale(HISTORY_LAYOUT),
            config.history_patch,
            config.token_size,
            config.token_heads,
            config.history_self_attention,
            hidden,
        )
        self.route_encoder = VectorSetEncoder(
            route_features,
            config.input_scale(ROUTE_LAYOUT),
            config.route_patch,
            config.token_size,
            config.token_heads,
            config.route_self_attention,
            hidden,
        )
        self.interaction = MaskedAttention(hidden, hidden, hidden, config.num_heads)
        self.interaction_norm = nn.LayerNorm(hidden)
        self.route_attention = MaskedAttention(hidden, hidden, hidden, config.num_heads)
        self.bev_encoder = _bev_cnn(bev_shape, config.bev_pool, config.bev_channels, hidden)
        self.register_buffer("goal_scale", config.input_scale(GOAL_LAYOUT), persistent=False)
        self.goal_encoder = nn.Sequential(
            nn.Linear(len(GOAL_LAYOUT), hidden), nn.ReLU(), nn.Linear(hidden, hidden)
        )

    @property
    def vehicle_feature_size(self) -> int:
        """Width 5L of a vehicle's concatenated features."""
        return 5 * self.config.hidden_size

    def encode(self, obs: Mapping[str, th.Tensor]) -> SceneFeatures:
        """Encode the goal-independent part of a batch of observations.

        :param obs: float tensors ``history`` (B, V, T_h, 9), ``history_mask`` (B, V, T_h),
            ``routes`` (B, V, N_r, N_p, 8), ``routes_mask`` (B, V, N_r, N_p), ``bev`` (B, C, H, W);
            other keys are ignored
        :return: the scenes' features
        """
        history, history_mask = obs["history"], obs["history_mask"]
        routes, routes_mask = obs["routes"], obs["routes_mask"]
        batch, vehicles, steps, _ = history.shape
        num_routes, points = routes.shape[2:4]
        present = (history_mask > 0).any(-1)  # (B, V)
        has_route = (routes_mask > 0).any(-1) & present[..., None]  # (B, V, N_r)

        rows = present.view(-1).nonzero().squeeze(1)
        f_history = self.history_encoder(
            history.reshape(batch * vehicles, steps, -1).index_select(0, rows),
            history_mask.reshape(batch * vehicles, steps).index_select(0, rows),
        )
        f_history = _scatter_rows(f_history, rows, batch * vehicles).view(batch, vehicles, -1)
        interaction = self.interaction(f_history, f_history, present)
        f_interaction = self.interaction_norm(f_history + interaction) * present[..., None].to(history.dtype)

        rows = has_route.view(-1).nonzero().squeeze(1)
        f_routes = self.route_encoder(
            routes.reshape(batch * vehicles * num_routes, points, -1).index_select(0, rows),
            routes_mask.reshape(batch * vehicles * num_routes, points).index_select(0, rows),
        )
        # Keys and values of the real routes only; the zero rows of the others are masked out.
        key_value = _scatter_rows(
            self.route_attention.key_value(f_routes), rows, batch * vehicles * num_routes
        )
        f_route = self.route_attention.attend(
            f_interaction.view(batch * vehicles, 1, -1),
            key_value.view(batch * vehicles, num_routes, -1),
            has_route.view(batch * vehicles, num_routes),
        ).view(batch, vehicles, -1)
        f_route = f_route * has_route.any(-1, keepdim=True).to(f_route.dtype)

        f_drivable = self.bev_encoder(obs["bev"].to(history.dtype))
        return SceneFeatures(f_history, f_interaction, f_route, f_drivable, present)

    def goal_features(self, goals: th.Tensor) -> th.Tensor:
        """Encode goal poses with the 2-layer goal MLP.

        :param goals: (..., 3) poses (x, y, heading) in the ego frame
        :return: (..., L) goal features f_g
        """
        return self.goal_encoder(goals * self.goal_scale)

    def vehicle_features(self, scene: SceneFeatures, goal_features: th.Tensor) -> th.Tensor:
        """Concatenate [history, interaction, route attention, drivable area, goal] per goal and vehicle.

        :param scene: the scenes' features (B scenes, V vehicles)
        :param goal_features: (B, G, L) features of G goals per scene
        :return: (B, G, V, 5L)
        """
        batch, vehicles, hidden = scene.history.shape
        goals = goal_features.shape[1]
        per_vehicle = th.cat((scene.history, scene.interaction, scene.route), -1)
        shape = (batch, goals, vehicles, hidden)
        return th.cat(
            (
                per_vehicle[:, None].expand(batch, goals, vehicles, 3 * hidden),
                scene.drivable[:, None, None].expand(shape),
                goal_features[:, :, None].expand(shape),
            ),
            -1,
        )

    def ego_features(self, scene: SceneFeatures, goal_features: th.Tensor) -> th.Tensor:
        """The ego's (vehicle 0's) concatenated 5L feature with one goal per scene.

        :param scene: the scenes' features
        :param goal_features: (B, L) goal features
        :return: (B, 5L)
        """
        return th.cat(
            (scene.history[:, 0], scene.interaction[:, 0], scene.route[:, 0], scene.drivable, goal_features),
            -1,
        )

    def forward(self, obs: Mapping[str, th.Tensor], goals: th.Tensor) -> th.Tensor:
        """Encode observations with G goals each: :meth:`encode` then :meth:`vehicle_features`.

        :param obs: see :meth:`encode`
        :param goals: (B, G, 3) goal poses in the ego frame
        :return: (B, G, V, 5L)
        """
        return self.vehicle_features(self.encode(obs), self.goal_features(goals))


def _scatter_rows(rows: th.Tensor, index: th.Tensor, total: int) -> th.Tensor:
    """(total, D) zeros with ``rows`` (n, D) placed at ``index`` (n,)."""
    return rows.new_zeros(total, rows.shape[1]).index_copy(0, index, rows)


def _bev_cnn(
    shape: tuple[int, int, int], pool: int, channels: tuple[int, ...], out_size: int
) -> nn.Sequential:
    """Average pooling, 3x3 stride-2 convolutions with ReLU, then a linear layer with ReLU to ``out_size``."""
    layers: list[nn.Module] = [nn.AvgPool2d(pool)] if pool > 1 else []
    previous = shape[0]
    for width in channels:
        layers += [nn.Conv2d(previous, width, 3, stride=2, padding=1), nn.ReLU()]
        previous = width
    convolutions = nn.Sequential(*layers, nn.Flatten())
    with th.no_grad():
        flat = convolutions(th.zeros(1, *shape)).shape[1]
    return nn.Sequential(convolutions, nn.Linear(flat, out_size), nn.ReLU())
