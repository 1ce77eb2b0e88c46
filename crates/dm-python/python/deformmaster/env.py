"""A Gymnasium environment over a fitted world model (docs/python.md).

Observation: the predicted positions of the bundle's tracked points,
(M, 3) float32 metres (with ``image_observation=True`` a dict that adds
the camera's RGB render). Action: each hand's displacement this frame,
(H, 3) float32 metres, at most ``max_hand_step_m`` per axis. Reward: minus
the one-directional L1 Chamfer distance (metres) from the goal cloud to
the predicted surface, the metric's Chamfer term. Episodes start at the
model's first frame with the hands where the bundle's first frame has
them (moved by a seeded Gaussian of ``hand_jitter_m``), and end after
``max_steps`` frames or when the simulation diverges.
"""

import numpy as np

try:
    import gymnasium as gym
    from gymnasium import spaces
except ImportError as error:  # pragma: no cover - depends on the install
    raise ImportError(
        "deformmaster.env needs gymnasium: pip install 'deformmaster[env]'"
    ) from error

from . import Bundle, Model, SimulationError, load_model, read_bundle

# Observations may sit on the domain's walls; the box is this much wider.
_BOX_MARGIN_M = 1e-3


class TwinEnv(gym.Env):
    """The fitted twin of one scene as a Gymnasium environment."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        model,
        bundle,
        goal=None,
        max_steps=None,
        max_hand_step_m=0.01,
        hand_jitter_m=0.0,
        image_observation=False,
        camera=0,
        render_mode=None,
        device="cpu",
    ):
        """``model``: a Model or a model directory; ``bundle``: a Bundle or
        a bundle directory (its first frame's hands, tracked points and
        cameras). ``goal``: (K, 3) target points; by default the tracked
        points visible at the bundle's last frame. ``max_steps``: frames
        per episode (default: the clip's length). ``camera``: the bundle
        camera index (or a camera dict) of renders and image observations.
        ``device``: where the simulation runs, as in ``Model.simulation``.
        """
        super().__init__()
        self.model = model if isinstance(model, Model) else load_model(model)
        self.bundle = bundle if isinstance(bundle, Bundle) else read_bundle(bundle)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode {render_mode!r}: use 'rgb_array' or None")
        self.render_mode = render_mode
        self.device = device
        tracks = self.bundle.tracks
        if goal is None:
            last = self.bundle.frame_count - 1
            goal = tracks["object_points"][last][tracks["object_visibility"][last]]
        self.goal = np.asarray(goal, dtype=np.float64).reshape(-1, 3)
        if len(self.goal) == 0:
            raise ValueError("goal has no points")
        self.max_steps = int(max_steps or self.bundle.frame_count - 1)
        self.max_hand_step_m = float(max_hand_step_m)
        self.hand_jitter_m = float(hand_jitter_m)
        self.image_observation = bool(image_observation)
        self.camera = camera if isinstance(camera, dict) else self.bundle.camera(camera)
        ids = self.model.track_particles(self.bundle)
        self._track_particles = ids[ids >= 0]
        self._first_hands = self.bundle.hand_anchors(0)

        origin, size = self.model.domain
        lo = np.asarray(origin, dtype=np.float64)
        self._hand_box = (lo, lo + size)
        points = spaces.Box(
            low=np.float32(lo.min() - _BOX_MARGIN_M),
            high=np.float32(lo.max() + size + _BOX_MARGIN_M),
            shape=(len(self._track_particles), 3),
            dtype=np.float32,
        )
        if self.image_observation:
            shape = (self.camera["height"], self.camera["width"], 3)
            self.observation_space = spaces.Dict(
                {"points": points, "image": spaces.Box(0, 255, shape, np.uint8)}
            )
        else:
            self.observation_space = points
        self.action_space = spaces.Box(
            low=-self.max_hand_step_m,
            high=self.max_hand_step_m,
            shape=self._first_hands.shape,
            dtype=np.float32,
        )
        self._sim = None
        self._steps = 0
        self._last_observation = None
        self._last_cost = 0.0

    def _observe(self):
        points = self._sim.points(self._track_particles)
        if not self.image_observation:
            return points
        return {"points": points, "image": self._sim.render(self.camera)["rgb"]}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        hands = self._first_hands.copy()
        if self.hand_jitter_m > 0.0:
            hands += self.np_random.normal(0.0, self.hand_jitter_m, size=hands.shape)
        self._sim = self.model.simulation(hands, device=self.device)
        self._steps = 0
        self._last_observation = self._observe()
        self._last_cost = self._sim.chamfer_to(self.goal)
        info = {"chamfer_m": self._last_cost, "frame": 0, "hands": self._sim.hands}
        return self._last_observation, info

    def step(self, action):
        if self._sim is None:
            raise RuntimeError("call reset() before step()")
        action = np.clip(
            np.asarray(action, dtype=np.float64).reshape(self._first_hands.shape),
            -self.max_hand_step_m,
            self.max_hand_step_m,
        )
        lo, hi = self._hand_box
        hands = np.clip(self._sim.hands + action, lo, hi)
        self._steps += 1
        truncated = self._steps >= self.max_steps
        try:
            self._sim.step(hands)
        except SimulationError as error:
            # The state is lost: end the episode on the last good observation.
            info = {"error": str(error), "frame": self._steps}
            return self._last_observation, -self._last_cost, True, truncated, info
        self._last_observation = self._observe()
        self._last_cost = self._sim.chamfer_to(self.goal)
        info = {"chamfer_m": self._last_cost, "frame": self._steps, "hands": self._sim.hands}
        return self._last_observation, -self._last_cost, False, truncated, info

    def render(self):
        if self.render_mode != "rgb_array" or self._sim is None:
            return None
        return self._sim.render(self.camera)["rgb"]
