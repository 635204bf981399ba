"""Pose-aware forecasting: the ego's own future poses, and the scene carried along them.

The forecast of a static world is the current frame resampled into each future ego frame
(:func:`renderworld.world.baselines.warp_along_poses`); with the ground-truth future poses it
reaches 50 / 47 / 42 % mIoU at 1 / 2 / 3 s on the mini fixture, against 28 / 19 / 14 % for a
constant-velocity warp: the gap is the ego's rotation. :class:`PoseHead` predicts those poses
(x, y, yaw) from the history poses, the current command and a bird's-eye view of the current
frame (where the road goes); :class:`PoseWarpWorldModel` adds the token network that forecasts
what the warp cannot know (newly revealed space, movers), reading the history brought into the
current frame (:func:`align_history`) and the warped frames.

Poses are (x, y, yaw) of an ego frame in the current ego frame (metres, radians; x forward,
y left), as :func:`renderworld.world.ego.frame_poses_from_poses` gives them.
"""

from __future__ import annotations

import torch
from torch import nn

from renderworld.constants import COMMANDS, GridSpec
from renderworld.world.baselines import constant_turn_rate_poses
from renderworld.world.config import WorldModelConfig
from renderworld.world.model import WorldModel
from renderworld.world.mover_head import MoverHead
from renderworld.world.movers import MOVERS
from renderworld.world.pose_agents import AGENT_FEATURES, LEADER_FEATURES, road_user_inputs
from renderworld.world.pose_ensemble import PoseEnsemble
from renderworld.world.pose_inputs import (
    BEV_GROUPS,
    align_history,
    bev_channels,
    invert_poses,
    kinematic_features,
    motion_channels,
)
from renderworld.world.pose_retime import LeaderRetiming, retime_along_path, stop_behind_leaders

__all__ = [
    "ANCHORS",
    "BEV_GROUPS",
    "PoseHead",
    "PoseWarpWorldModel",
    "align_history",
    "bev_channels",
    "invert_poses",
    "kinematic_features",
    "motion_channels",
    "pose_loss",
]

#: Extrapolations a :class:`PoseHead` predicts residuals on.
ANCHORS = ("ctr", "ctr_cv")


class PoseHead(nn.Module):
    """Future ego poses from the history poses, the command and the current bird's-eye view.

    One mode of S poses per command (the current command selects it), each a residual on an
    extrapolation of the history: ``anchors="ctr"`` constant turn rate (the last layer starts at
    zero, so an untrained head predicts constant turn rate); ``"ctr_cv"`` a learned per-step
    blend of constant turn rate and constant velocity with the heading fixed (half each at
    initialisation), so that both "the turn goes on" and "the turn has ended" are a saturated
    weight away instead of a large residual.

    Args:
        history: H history frames.
        steps: S future frames.
        bev_in: channels of the bird's-eye view (``len(BEV_GROUPS)``).
        hidden: width of the MLP.
        anchors: the extrapolations it predicts residuals on (:data:`ANCHORS`).
        kinematics: also read :func:`kinematic_features` of the history (step lengths, their
            changes and the heading changes on a log-like scale), so that the small differences
            that say when a turn starts or ends (a 0.3-degree heading change, a 0.5 m/s speed
            drop) are not lost among inputs of order one.
        motion_frames: the bird's-eye view also holds :func:`motion_channels` of this many
            frames before the current one (0: the current frame only), so that the head sees
            how the others move (a lead car braking, a car cutting in).
        agents: the head also reads :func:`~renderworld.world.pose_agents.agent_features` of
            this many tracked movers (0: none): where the nearest road users are and how fast
            they move.
        leader: a :class:`~renderworld.world.pose_retime.LeaderRetiming` also reads
            :func:`~renderworld.world.pose_agents.leader_features` (after the agents' rows:
            the road user in its corridor ahead and the first one foreseen to enter it, what a
            driver brakes for) and retimes the plan along its own path: the leader changes how
            far the ego gets, not where the path goes.
        bev_pool: the bird's-eye features are pooled to ``bev_pool x bev_pool`` cells before
            the MLP (4: 20 m cells on the 80 m grid; finer says better where a junction
            begins).
    """

    #: Scale of the raw outputs: metres for x / y, radians for yaw.
    SCALE = (4.0, 4.0, 0.5)

    def __init__(
        self,
        history: int,
        steps: int,
        bev_in: int = len(BEV_GROUPS),
        hidden: int = 128,
        anchors: str = "ctr",
        kinematics: bool = False,
        motion_frames: int = 0,
        agents: int = 0,
        bev_pool: int = 4,
        leader: bool = False,
    ):
        super().__init__()
        if history < 2 or steps < 1:
            raise ValueError(f"history/steps: expected >= 2 / >= 1, got {history}/{steps}")
        if anchors not in ANCHORS:
            raise ValueError(f"anchors: expected one of {ANCHORS}, got {anchors!r}")
        self.history, self.steps, self.anchors = history, steps, anchors
        self.kinematics = bool(kinematics)
        if not 0 <= motion_frames < history:
            raise ValueError(f"motion_frames: expected 0..{history - 1}, got {motion_frames}")
        self.motion_frames = int(motion_frames)
        if not isinstance(agents, int) or isinstance(agents, bool) or agents < 0:
            raise ValueError(f"agents: expected an int >= 0, got {agents!r}")
        self.agents = agents
        if not isinstance(leader, bool):
            raise ValueError(f"leader: expected true or false, got {leader!r}")
        self.leader = leader
        if not isinstance(bev_pool, int) or isinstance(bev_pool, bool) or bev_pool < 1:
            raise ValueError(f"bev_pool: expected an int >= 1, got {bev_pool!r}")
        self.bev_pool = bev_pool
        bev_in += self.motion_frames
        n_out = 3 + (1 if anchors == "ctr_cv" else 0)  # (dx, dy, dyaw) [+ CTR-vs-CV logit]
        self.bev = nn.Sequential(
            nn.Conv2d(bev_in, 16, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.GELU(),
            nn.AdaptiveAvgPool2d(bev_pool), nn.Flatten(), nn.Linear(32 * bev_pool**2, hidden),
            nn.GELU(),
        )  # fmt: skip
        n_in = 4 * history + len(COMMANDS) + hidden
        n_in += kinematic_features(torch.zeros(1, history, 3)).shape[1] if self.kinematics else 0
        n_in += agents * AGENT_FEATURES
        self.mlp = nn.Sequential(
            nn.Linear(n_in, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
            nn.Linear(hidden, len(COMMANDS) * steps * n_out),
        )  # fmt: skip
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.retime = LeaderRetiming(history, steps, LEADER_FEATURES) if leader else None
        self.register_buffer("scale", torch.tensor(self.SCALE), persistent=False)

    @property
    def road_user_features(self) -> int:
        """Width of the ``agents`` input: the agents' rows, then the leader's."""
        return self.agents * AGENT_FEATURES + (LEADER_FEATURES if self.leader else 0)

    def forward(
        self,
        history_poses: torch.Tensor,
        command: torch.Tensor,
        bev: torch.Tensor,
        agents: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict the future poses.

        Args:
            history_poses: [B, H, 3] (x, y, yaw) of frames t-H+1..t in the current ego frame.
            command: [B] int64 index into ``COMMANDS`` (the current command).
            bev: [B, C, X, Y] :func:`bev_channels` of the current frame (then, with
                ``motion_frames``, :func:`motion_channels`).
            agents: [B, agents * AGENT_FEATURES (+ LEADER_FEATURES)] :func:`agent_features`
                then :func:`leader_features` when the head reads them, else None.

        Returns:
            (poses [B, S, 3] of the command's mode, modes [B, len(COMMANDS), S, 3]).
        """
        b = history_poses.shape[0]
        if tuple(history_poses.shape) != (b, self.history, 3):
            raise ValueError(
                f"history_poses: expected [B, {self.history}, 3], got {tuple(history_poses.shape)}"
            )
        if tuple(command.shape) != (b,) or command.dtype != torch.int64:
            raise ValueError(
                f"command: expected int64 [{b}], got {command.dtype} {tuple(command.shape)}"
            )
        hp = history_poses.float()
        feats = torch.cat(
            [hp[..., :2] / 10.0, torch.sin(hp[..., 2:]), torch.cos(hp[..., 2:])], dim=-1
        ).flatten(1)
        onehot = nn.functional.one_hot(command, len(COMMANDS)).float()
        parts = [feats, onehot, self.bev(bev.float())]
        if self.kinematics:
            parts.append(kinematic_features(hp))
        if self.road_user_features:
            want = (b, self.road_user_features)
            if agents is None or tuple(agents.shape) != want:
                raise ValueError(
                    f"agents: the head reads {self.agents} agents and leader={self.leader}; "
                    f"expected {list(want)}, got "
                    f"{None if agents is None else tuple(agents.shape)}"
                )
            parts.append(agents[:, : self.agents * AGENT_FEATURES].float())
        x = torch.cat(parts, dim=1)
        out = self.mlp(x).view(b, len(COMMANDS), self.steps, -1)
        raw = out[..., :3] * self.scale
        hist = history_poses.detach().double()
        prior = constant_turn_rate_poses(hist, self.steps).float()[:, None]
        if self.anchors == "ctr_cv":
            # Constant velocity, heading fixed: CTR with the last heading change set to zero.
            still = hist.clone()
            still[:, :, 2] = 0.0
            cv = constant_turn_rate_poses(still, self.steps).float()[:, None]
            w = torch.sigmoid(out[..., 3:])  # weight of CTR; 0.5 at initialisation
            prior = w * prior + (1.0 - w) * cv
        modes = prior + raw
        if self.retime is not None:
            factors = self.retime(feats, onehot, agents[:, self.agents * AGENT_FEATURES :])
            modes = retime_along_path(modes, factors)
        idx = command.view(b, 1, 1, 1).expand(b, 1, self.steps, 3)
        return modes.gather(1, idx).squeeze(1), modes


def pose_loss(pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor | None = None,
              yaw_weight: float = 5.0, step_weights: torch.Tensor | None = None,
              ) -> dict[str, torch.Tensor]:  # fmt: skip
    """Pose error: Euclidean position error (m) + ``yaw_weight`` x |wrapped yaw error| (rad).

    Args:
        pred, gt: [B, S, 3] (x, y, yaw).
        valid: [B, S] bool or None.
        yaw_weight: metres per radian.
        step_weights: [S] weight of each future step (None: all 1); the mean is over valid
            steps weighted by them.

    Returns:
        ``pose_l2`` (metres, mean over valid steps), ``pose_yaw`` (radians), ``pose``
        (their weighted sum).
    """
    if pred.shape != gt.shape or pred.shape[-1] != 3:
        raise ValueError(
            f"pred/gt: expected equal [B, S, 3], got {tuple(pred.shape)}, {tuple(gt.shape)}"
        )
    w = torch.ones(pred.shape[:2], device=pred.device) if valid is None else valid.float()
    if step_weights is not None:
        if tuple(step_weights.shape) != (pred.shape[1],):
            raise ValueError(
                f"step_weights: expected [{pred.shape[1]}], got {tuple(step_weights.shape)}"
            )
        w = w * step_weights.to(w)
    denom = w.sum().clamp_min(1.0)
    g = gt.to(pred.dtype)
    l2 = torch.sqrt(((pred[..., :2] - g[..., :2]) ** 2).sum(-1) + 1e-12) - 1e-6
    d = pred[..., 2] - g[..., 2]
    yaw = torch.atan2(torch.sin(d), torch.cos(d)).abs()
    l2, yaw = (l2 * w).sum() / denom, (yaw * w).sum() / denom
    return {"pose_l2": l2, "pose_yaw": yaw, "pose": l2 + yaw_weight * yaw}


class PoseWarpWorldModel(nn.Module):
    """:class:`PoseHead` + a token world model over the aligned history and the warped frames.

    The token network (:class:`renderworld.world.WorldModel`, causal in time) reads a sequence
    of ``history - 1`` aligned history frames (t-H+1..t-1 in the current ego frame) followed by
    the S warped frames (the current frame carried along the future poses, each in its own
    future ego frame); the output at warped frame k scores the codes of frame t+k. A learned
    per-codebook bonus on the logit of each cell's warped code makes "the warp is right" the
    starting point; the network learns where it is not.

    Args:
        config: the token network's :class:`WorldModelConfig` (``max_frames`` = H + S - 1 is
            exactly this sequence's length).
        copy_bonus: initial logit bonus of the warped code.
        anchors: the pose head's extrapolations (:data:`ANCHORS`).
        movers: how the forecast moves other road users (``"static"``, ``"object_cv"`` or
            ``"learned"``, :mod:`renderworld.world.forecast`); only ``"learned"`` has weights,
            its :attr:`mover_head` (:class:`~renderworld.world.mover_head.MoverHead`).
        kinematics: the pose head also reads :func:`kinematic_features` of the history.
        motion_frames: the pose head also reads :func:`motion_channels` of this many frames.
        agents: the pose head also reads :func:`agent_features` of this many tracked movers.
        bev_pool: the pose head's bird's-eye readout cells per side (:class:`PoseHead`).
        leader: the pose head also reads :func:`leader_features`.
        leader_stop: at prediction time (eval mode, not with ``members``), the command's plan
            (not the other ``modes``) stops behind a leader that brakes hard or has come to a stand
            (:func:`~renderworld.world.pose_retime.stop_behind_leaders`); training is unchanged.
        pose_heads: how many pose heads (more than one: a
            :class:`~renderworld.world.pose_ensemble.PoseEnsemble`, each member initialised
            from its own seed, the global RNG left as one head leaves it).
    """

    def __init__(
        self,
        config: WorldModelConfig,
        copy_bonus: float = 2.0,
        anchors: str = "ctr",
        movers: str = "static",
        kinematics: bool = False,
        motion_frames: int = 0,
        agents: int = 0,
        pose_heads: int = 1,
        bev_pool: int = 4,
        leader: bool = False,
        leader_stop: bool = False,
    ):
        super().__init__()
        if not isinstance(config, WorldModelConfig):
            raise TypeError(f"config: expected WorldModelConfig, got {type(config).__name__}")
        if movers not in MOVERS:
            raise ValueError(f"movers: expected one of {MOVERS}, got {movers!r}")
        self.config = config
        #: How the forecast moves other road users (:data:`renderworld.world.movers.MOVERS`).
        self.movers = movers
        if not isinstance(leader_stop, bool):
            raise ValueError(f"leader_stop: expected true or false, got {leader_stop!r}")
        #: Plans stop behind a leader coming to a stop, at prediction time.
        self.leader_stop = leader_stop
        self.net = WorldModel(config)
        if not isinstance(pose_heads, int) or isinstance(pose_heads, bool) or pose_heads < 1:
            raise ValueError(f"pose_heads: expected an int >= 1, got {pose_heads!r}")

        def head() -> PoseHead:
            return PoseHead(
                config.history_frames, config.future_frames, anchors=anchors,
                kinematics=kinematics, motion_frames=motion_frames, agents=agents,
                bev_pool=bev_pool, leader=leader,
            )  # fmt: skip

        self.pose: PoseHead | PoseEnsemble = head()
        if pose_heads > 1:
            members, seed = [self.pose], torch.initial_seed()
            with torch.random.fork_rng(devices=[]):
                for k in range(1, pose_heads):
                    torch.manual_seed(seed + 7919 * k)
                    members.append(head())
            self.pose = PoseEnsemble(members)
        self.copy_bonus = nn.Parameter(torch.full((config.num_codebooks,), float(copy_bonus)))
        #: The learned mover motion (``movers="learned"``), else None.
        self.mover_head = (
            MoverHead(config.history_frames, config.future_frames) if movers == "learned" else None
        )

    def predict_poses(
        self,
        history_poses: torch.Tensor,
        command: torch.Tensor,
        current: torch.Tensor,
        history: torch.Tensor | None = None,
        grid: GridSpec | None = None,
        members: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Future poses [B, S, 3] (and every command's [B, C, S, 3]) from the history poses, the
        current frame and the command.

        Args:
            history_poses: [B, H, 3]; command: [B] int64; current: [B, X, Y, Z] labels of the
                current frame.
            history: [B, H, X, Y, Z] labels of the history frames (the last is ``current``) and
                grid: their grid; needed when the pose head reads ``motion_frames`` or
                ``agents`` or ``leader``.
            members: each pose head's own prediction instead, [K, B, S, 3] and
                [K, B, C, S, 3] (K = 1 for a single head), for training each on its loss.

        Raises:
            ValueError: naming ``history`` when the head reads motion and it or ``grid`` is
                missing.
        """
        bev = bev_channels(current)
        frames = self.pose.motion_frames
        if frames:
            if history is None or grid is None:
                raise ValueError(
                    f"history: the pose head reads motion_frames={frames}; pass the history "
                    "frames and their grid"
                )
            motion = motion_channels(history, history_poses, grid, frames)
            bev = torch.cat([bev, motion.to(bev.device)], dim=1)
        agents = road_user_inputs(self.pose, history, history_poses, grid)
        if not members:
            poses, modes = self.pose(history_poses, command, bev, agents)
            if self.leader_stop and not self.training:
                if history is None or grid is None:
                    raise ValueError("history: leader_stop needs the history frames and their grid")
                poses = stop_behind_leaders(poses, history, history_poses, grid)
            return poses, modes
        if isinstance(self.pose, PoseEnsemble):
            return self.pose.members_forward(history_poses, command, bev, agents)
        poses, modes = self.pose(history_poses, command, bev, agents)
        return poses[None], modes[None]

    def forward(
        self, tokens: torch.Tensor, sequence_poses: torch.Tensor, command: torch.Tensor
    ) -> list[torch.Tensor]:
        """Code logits of the future frames.

        Args:
            tokens: [B, H-1+S, G, h, w] int64: aligned history codes, then warped-frame codes.
            sequence_poses: [B, H-1+S, 3] pose of each sequence frame in the current ego
                frame (history poses, then the future poses the frames were warped to).
            command: [B] int64.

        Returns:
            G tensors [B, S, K_g, h, w]: index k-1 scores frame t+k (views of codes-last
            memory: ``lg.permute(0, 1, 3, 4, 2)`` is contiguous, for a cross-entropy over rows).
        """
        h = self.config.history_frames
        if tokens.dim() != 5 or tokens.shape[1] < h:
            raise ValueError(f"tokens: expected [B, >= {h}, G, h, w], got {tuple(tokens.shape)}")
        disp = torch.diff(sequence_poses[..., :2].float(), dim=1)
        out = self.net(tokens, disp, command, logits_from=h - 1)  # the history's are unscored
        logits = []
        for g, lg in enumerate(out.logits):
            # The heads write codes last in memory: add the bonus there (a plain copy, not a
            # transposing one) and hand back the [B, S, K, h, w] view of it.
            own = tokens[:, h - 1 :, g, :, :, None]
            bonus = self.copy_bonus[g].to(lg.dtype).expand_as(own)
            logits.append(
                lg.permute(0, 1, 3, 4, 2).scatter_add(-1, own, bonus).permute(0, 1, 4, 2, 3)
            )
        return logits
