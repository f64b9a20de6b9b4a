"""A numpy-only image maze with gym-maze's rules.

Layouts: a perfect maze carved by a recursive backtracker (iterative, seeded by the layout id and the size),
plus ``max(1, round(0.1 * N * N))`` extra openings that add loops. Same (size, layout id) → same maze.
Layout ids ``[0, HELDOUT_LAYOUT_START)`` are demonstration layouts; ids from ``HELDOUT_LAYOUT_START`` on are
held out for evaluation on mazes never seen in training. A reset with ``seed`` s plays layout
``layout_start + s mod num_layouts`` (or ``options["layout_id"]``); an unseeded reset draws one.

Rules: start at the top-left cell, goal at the bottom-right; actions 0=N, 1=S, 2=E, 3=W; a move into a wall
leaves the agent in place but still counts as a step; reward +1 on entering the goal (episode ends) and
−0.1/(N·N) for every other step. The step cap (``10 · N · N`` by default) is applied by ``gym.make``'s
``max_episode_steps``. Observation: ``{"pixels": uint8 (H, W, 3)}`` — walls black, floor white, goal green,
agent red.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from lerobot_iupe.envs.classic import action_to_index

HELDOUT_LAYOUT_START = 1_000_000
MOVES = np.array([(-1, 0), (1, 0), (0, 1), (0, -1)])  # N, S, E, W as (d_row, d_col)
ACTION_NAMES = ("N", "S", "E", "W")


def default_max_steps(size: int) -> int:
    return 10 * size * size


@dataclass(frozen=True)
class MazeLayout:
    """``open[r, c, a]`` is True when action ``a`` from cell (r, c) leads to a neighbouring cell."""

    size: int
    layout_id: int
    open: np.ndarray

    @classmethod
    def generate(cls, size: int, layout_id: int) -> MazeLayout:
        if size < 2:
            raise ValueError(f"maze size must be at least 2, got {size}")
        rng = np.random.default_rng([size, layout_id])
        passage = np.zeros((size, size, 4), dtype=bool)

        def carve(r: int, c: int, a: int) -> None:
            dr, dc = MOVES[a]
            passage[r, c, a] = True
            passage[r + dr, c + dc, a ^ 1] = True  # N<->S, E<->W are 0<->1 and 2<->3

        visited = np.zeros((size, size), dtype=bool)
        visited[0, 0] = True
        stack = [(0, 0)]
        while stack:
            r, c = stack[-1]
            options = [
                a
                for a, (dr, dc) in enumerate(MOVES)
                if 0 <= r + dr < size and 0 <= c + dc < size and not visited[r + dr, c + dc]
            ]
            if not options:
                stack.pop()
                continue
            a = int(rng.choice(options))
            carve(r, c, a)
            stack.append((r + MOVES[a][0], c + MOVES[a][1]))
            visited[stack[-1]] = True
        walls = [
            (r, c, a)
            for r in range(size)
            for c in range(size)
            for a in (1, 2)
            if (r + MOVES[a][0] < size and c + MOVES[a][1] < size) and not passage[r, c, a]
        ]
        n_extra = min(len(walls), max(1, round(0.1 * size * size)))
        for i in rng.choice(len(walls), size=n_extra, replace=False):
            carve(*walls[i])
        return cls(size, layout_id, passage)

    def shortest_path_actions(self, goal: tuple[int, int]) -> np.ndarray:
        """BFS from the goal: ``result[r, c]`` is an action on a shortest path from (r, c) to the goal."""
        best = np.full((self.size, self.size), -1, dtype=np.int64)
        dist = np.full((self.size, self.size), -1, dtype=np.int64)
        dist[goal] = 0
        queue = deque([goal])
        while queue:
            r, c = queue.popleft()
            for a, (dr, dc) in enumerate(MOVES):
                if self.open[r, c, a] and dist[r + dr, c + dc] < 0:
                    dist[r + dr, c + dc] = dist[r, c] + 1
                    best[r + dr, c + dc] = a ^ 1  # step back along the edge we came through
                    queue.append((r + dr, c + dc))
        return best

    def block_image(self) -> np.ndarray:
        """(2N+1, 2N+1) map: 1 for floor, 0 for wall."""
        n = self.size
        grid = np.zeros((2 * n + 1, 2 * n + 1), dtype=np.uint8)
        grid[1::2, 1::2] = 1
        grid[2:-1:2, 1::2] = self.open[:-1, :, 1]
        grid[1::2, 2:-1:2] = self.open[:, :-1, 2]
        return grid


class MazeEnv(gym.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        size: int = 5,
        image_size: int = 64,
        layout_start: int = 0,
        num_layouts: int = 100,
        render_mode: str | None = "rgb_array",
    ):
        if size < 2:
            raise ValueError(f"maze size must be at least 2, got {size}")
        if image_size < 2 * size + 1:
            raise ValueError(f"image_size {image_size} cannot show a {size}x{size} maze (need >= {2 * size + 1})")
        if num_layouts < 1:
            raise ValueError(f"num_layouts must be at least 1, got {num_layouts}")
        self.size, self.image_size = size, image_size
        self.layout_start, self.num_layouts = layout_start, num_layouts
        self.render_mode = render_mode
        self.goal = (size - 1, size - 1)
        self.step_penalty = -0.1 / (size * size)
        self.observation_space = gym.spaces.Dict(
            {"pixels": gym.spaces.Box(0, 255, (image_size, image_size, 3), dtype=np.uint8)}
        )
        self.action_space = gym.spaces.Discrete(4)
        self.task = f"maze{size}"
        self.task_description = f"Walk from the top-left cell to the bottom-right cell of the {size}x{size} maze."
        # block index of every pixel row/column: nearest-neighbour scaling of the (2N+1)^2 block map
        self._pixel_block = (np.arange(image_size) * (2 * size + 1)) // image_size
        self.layout: MazeLayout | None = None
        self.agent = (0, 0)

    def _load_layout(self, layout_id: int) -> None:
        if self.layout is None or self.layout.layout_id != layout_id:
            self.layout = MazeLayout.generate(self.size, layout_id)
            self._expert_actions = self.layout.shortest_path_actions(self.goal)
            blocks = self.layout.block_image()
            colours = np.where(blocks[..., None] == 1, 255, 0).astype(np.uint8).repeat(3, axis=-1)
            colours[2 * self.goal[0] + 1, 2 * self.goal[1] + 1] = (0, 200, 0)
            self._background = colours

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        layout_id = options.get("layout_id")
        if layout_id is None and seed is not None:
            # Any num_layouts consecutive seeds cover every layout once (100 evaluation episodes: 100 mazes).
            layout_id = self.layout_start + seed % self.num_layouts
        elif layout_id is None:
            layout_id = self.layout_start + int(self.np_random.integers(self.num_layouts))
        self._load_layout(int(layout_id))
        if options.get("random_start", False):
            cell = int(self.np_random.integers(self.size * self.size - 1))  # any cell but the goal
            self.agent = divmod(cell, self.size)
        else:
            self.agent = (0, 0)
        return self._observation(), self._info(False)

    def step(self, action):
        a = action_to_index(action, 4)
        r, c = self.agent
        if self.layout.open[r, c, a]:
            self.agent = (r + int(MOVES[a][0]), c + int(MOVES[a][1]))
        reached = self.agent == self.goal
        reward = 1.0 if reached else self.step_penalty
        return self._observation(), reward, reached, False, self._info(reached)

    def expert_action(self) -> int:
        """An action on a shortest path to the goal from the current cell (BFS)."""
        return int(self._expert_actions[self.agent])

    def _info(self, success: bool) -> dict:
        return {"is_success": success, "layout_id": self.layout.layout_id, "agent_cell": self.agent}

    def _observation(self) -> dict[str, np.ndarray]:
        return {"pixels": self.render()}

    def render(self) -> np.ndarray:
        blocks = self._background.copy()
        blocks[2 * self.agent[0] + 1, 2 * self.agent[1] + 1] = (220, 0, 0)
        return blocks[self._pixel_block][:, self._pixel_block]
