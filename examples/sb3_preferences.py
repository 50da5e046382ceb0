"""A Stable-Baselines3 agent trained on people's preferences, gathered by a sepoa server.

SAC learns gymnasium's HalfCheetah-v5 without its reward. In rounds, the example picks pairs of
its own segments, renders each off-screen from its stored physics states (EGL, falling back to
OSMesa, as the app's own clips), asks people which is better through `sepoa.client`, waits for
their answers, trains the preference reward model of the app's own trainer
(`trainer.reward_model`'s ensemble, Bradley-Terry) on every answer so far, rewrites the rewards
in SAC's replay buffer with it, and lets SAC train on that reward until the next round. The
environment's own reward is never trained on: it travels, hidden from labellers, as each pair's
true returns (for the run's accuracy and calibration pages) and into the summary at the end.

    # an external run and its token (an operator's calls, docs/EXTERNAL.md), then
    python examples/sb3_preferences.py --url http://127.0.0.1:8000 --token run.1.Xq... --run 7

and answer its pairs on the label page (`/label?run=7`). `--preset tiny` is the seconds-long
version the tests run, with a scripted labeller answering over the label API. `--summary`
writes what the run came to as JSON: answers used, the learned reward's ordering of held-out
segments (ones asked of nobody) against their true returns, SAC's updates and true returns.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import SAC
from stable_baselines3.common.logger import Logger

from runvocab.config import RewardConfig
from sepoa.client import Pair, Study, StudyError
from trainer.clips import ClipConfig, render_quality
from trainer.doctor import choose_backend
from trainer.reward_model import LabelledPairs, RewardModel

ANSWER_TARGETS = {"first": 0.0, "second": 1.0, "equal": 0.5}
"""an aggregate answer as the reward model's target, P[second better]; cant_tell and skip
are dropped"""


@dataclass(frozen=True)
class Args:
    """What the example does; every field is a command-line flag (`--pairs-per-round 20`)."""

    url: str = "http://127.0.0.1:8000"
    """the sepoa server"""
    token: str = ""
    """the external run's token (POST /api/runs/{id}/tokens)"""
    run: int = 0
    """the external run's id"""
    env_id: str = "HalfCheetah-v5"
    """the gymnasium MuJoCo task"""
    seed: int = 0
    """seeds the environment, SAC, the reward model and the pairs drawn"""
    rounds: int = 10
    """rounds of asking: pairs pushed, answers awaited, the reward model trained"""
    pairs_per_round: int = 20
    """pairs of segments asked per round"""
    segment: int = 50
    """steps per segment: a clip of as many frames"""
    size: int = 256
    """the clips' side in pixels (even, 64 to 512)"""
    first_steps: int = 2_000
    """steps of random actions before the first round"""
    steps_per_round: int = 5_000
    """SAC's steps (one update each) on the learned reward after each round"""
    net_width: int = 256
    """SAC's and the reward model's hidden layer width"""
    batch_size: int = 256
    """SAC's batch size"""
    held_out: int = 200
    """segments of the last phase, asked of nobody, the learned reward is checked on"""
    answer_timeout: float = 0.0
    """seconds to wait for a round's answers (0: as long as it takes)"""
    cursor_file: str = ""
    """keeps the answers cursor, so a restarted example reads on from it ("": none)"""
    summary: str = ""
    """writes what the run came to here, as JSON ("": printed only)"""
    threads: int = 1
    """torch threads (one per process where processes share the cores)"""
    progress: bool = True
    """a tqdm bar while answers come in"""


PRESETS = {
    "default": Args(),
    # The tests' seconds-long run: tiny clips, two small rounds, a few hundred SAC updates.
    "tiny": Args(rounds=2, pairs_per_round=8, segment=20, size=64, first_steps=400,
                 steps_per_round=300, net_width=64, batch_size=64, held_out=60,
                 answer_timeout=120.0, progress=False),
}


def field_docs(cls: type) -> dict[str, str]:
    """Each field's docstring (the string under it), for --help."""
    tree = ast.parse(Path(__file__).read_text())
    [node] = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls.__name__]
    docs = {}
    for stmt, after in zip(node.body, node.body[1:], strict=False):
        if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name) and \
                isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
            docs[stmt.target.id] = str(after.value.value)
    return docs


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", choices=sorted(PRESETS), default="default",
                        help="the defaults the other flags change")
    docs = field_docs(Args)
    for f in dataclasses.fields(Args):
        flag = "--" + f.name.replace("_", "-")
        if f.type == "bool":
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, help=docs[f.name])
        else:
            kind = {"int": int, "float": float}.get(str(f.type), str)
            parser.add_argument(flag, type=kind, help=docs[f.name])
    given = vars(parser.parse_args(argv))
    preset = PRESETS[given.pop("preset")]
    return dataclasses.replace(preset, **{k: v for k, v in given.items() if v is not None})


class Steps:
    """Every step the agent took, as the reward model and the clips need them."""

    def __init__(self) -> None:
        self.obs_action: list[np.ndarray] = []
        self.true_reward: list[float] = []
        self.state: list[tuple[np.ndarray, np.ndarray]] = []
        """(qpos, qvel) before the step: the frame that shows it"""
        self.episode: list[int] = []

    def __len__(self) -> int:
        return len(self.true_reward)

    def starts(self, length: int, rng: np.random.Generator, n: int, since: int = 0) -> np.ndarray:
        """`n` segment starts at or after step `since`, each segment within one episode."""
        episode = np.asarray(self.episode)
        last = len(self) - length
        ok = np.flatnonzero(episode[since:last + 1] == episode[since + length - 1:])
        return since + rng.choice(ok, size=n, replace=len(ok) < n)

    def segment(self, start: int, length: int) -> np.ndarray:
        """(length, obs_dim + action_dim) float32: what the reward model reads."""
        return np.stack(self.obs_action[start:start + length])

    def true_return(self, start: int, length: int) -> float:
        return float(np.sum(self.true_reward[start:start + length]))


class Preferences:
    """The app's preference reward model (`trainer.reward_model`) on the answers so far. It
    reads (obs, action) standardised by the random steps' mean and std: unscaled, a few joint
    velocities of tens drown the forward speed, and with tens of answers standardised inputs
    order held-out segments far better (0.85-0.9 of pairs against 0.55-0.75)."""

    def __init__(self, obs_dim: int, action_dim: int, width: int, seed: int):
        cfg = RewardConfig(hidden_dim=width, hidden_layers=2 if width < 256 else 3)
        self.model = RewardModel(obs_dim, action_dim, cfg, torch.device("cpu"), seed)
        self.pairs = LabelledPairs()
        self.mean, self.std = np.zeros(obs_dim + action_dim), np.ones(obs_dim + action_dim)

    def standardise_by(self, obs_action: np.ndarray) -> None:
        self.mean, self.std = obs_action.mean(0), obs_action.std(0) + 1e-6

    def features(self, obs_action: np.ndarray) -> np.ndarray:
        return ((obs_action - self.mean) / self.std).astype(np.float32)

    def add(self, first: np.ndarray, second: np.ndarray, answer: str) -> bool:
        """One pair's aggregate answer; False for one that says nothing (cant_tell, skip)."""
        target = ANSWER_TARGETS.get(answer)
        if target is not None:
            self.pairs.add(self.features(first), self.features(second), target)
        return target is not None

    def train(self) -> dict[str, float]:
        return self.model.train_round(self.pairs) if len(self.pairs) else {}

    def reward(self, obs_action: np.ndarray) -> np.ndarray:
        """The learned reward (the ensemble's mean) of (n, obs + action) steps; 0 before any
        answer."""
        if not len(self.pairs):
            return np.zeros(len(obs_action), np.float32)
        x = torch.as_tensor(self.features(obs_action))
        return self.model.member_rewards(x).mean(0).numpy()


class LearnedReward(gym.Wrapper):
    """Records each step in `steps` and gives the agent the learned reward in place of the
    environment's (which goes on in `info["true_reward"]`)."""

    def __init__(self, env: gym.Env, steps: Steps, preferences: Preferences):
        super().__init__(env)
        self.steps, self.preferences = steps, preferences
        self.episodes, self.true_return = -1, 0.0
        self.true_returns: list[float] = []
        """the true return of each finished episode"""

    def reset(self, **kwargs: Any) -> Any:
        self.episodes, self.true_return = self.episodes + 1, 0.0
        self.last_obs, info = self.env.reset(**kwargs)
        return self.last_obs, info

    def step(self, action: np.ndarray) -> Any:
        data = self.env.unwrapped.data  # type: ignore[attr-defined]
        state = (data.qpos.copy(), data.qvel.copy())
        obs, true_reward, terminated, truncated, info = self.env.step(action)
        obs_action = np.concatenate([self.last_obs, action]).astype(np.float32)
        self.steps.obs_action.append(obs_action)
        self.steps.true_reward.append(float(true_reward))
        self.steps.state.append(state)
        self.steps.episode.append(self.episodes)
        self.true_return += float(true_reward)
        if terminated or truncated:
            self.true_returns.append(self.true_return)
        self.last_obs = obs
        reward = float(self.preferences.reward(obs_action[None])[0])
        return obs, reward, terminated, truncated, info | {"true_reward": true_reward}


class Film:
    """Segments' clips, re-rendered from their physics states in an environment of its own,
    by the camera that follows the body, at the app's clip render quality."""

    def __init__(self, env_id: str, size: int, seed: int):
        self.env = gym.make(env_id, render_mode="rgb_array", width=size, height=size,
                            camera_name="track")
        self.env.reset(seed=seed)
        quality = self.env.unwrapped.model.vis.quality  # type: ignore[attr-defined]
        for name, value in render_quality(ClipConfig(width=size, height=size)).items():
            setattr(quality, name, value)

    def frames(self, states: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """uint8 (frames, size, size, 3)"""
        shot = []
        for qpos, qvel in states:
            self.env.unwrapped.set_state(qpos, qvel)  # type: ignore[attr-defined]
            shot.append(self.env.render())
        return np.stack(shot)  # type: ignore[arg-type]


def relabel(agent: SAC, preferences: Preferences) -> None:
    """SAC's replay buffer keeps the rewards it was given: rewrite them with the new model."""
    buffer = agent.replay_buffer
    assert buffer is not None
    n = buffer.buffer_size if buffer.full else buffer.pos
    obs_action = np.concatenate([buffer.observations[:n, 0], buffer.actions[:n, 0]], axis=1)
    buffer.rewards[:n, 0] = preferences.reward(obs_action)


def ask_round(study: Study, steps: Steps, film: Film, preferences: Preferences, args: Args,
              round_: int, rng: np.random.Generator) -> tuple[int, int]:
    """One round: pairs of segments drawn from every step so far, their clips pushed, their
    answers awaited and added; how many were asked and how many answers say something."""
    h = args.segment
    starts = steps.starts(h, rng, 2 * args.pairs_per_round).reshape(-1, 2)
    pairs = [Pair(film.frames(steps.state[a:a + h]), film.frames(steps.state[b:b + h]),
                  returns=(steps.true_return(a, h), steps.true_return(b, h)),
                  meta={"round": round_, "starts": [int(a), int(b)]}) for a, b in starts]
    queries = study.ask(pairs)
    print(f"round {round_}: asked {len(queries)} pairs; waiting for their answers", flush=True)
    answers = study.wait_for(queries, timeout=args.answer_timeout or None)
    used = sum(preferences.add(steps.segment(a, h), steps.segment(b, h), answers[query.key])
               for query, (a, b) in zip(queries, starts, strict=True))
    return len(queries), used


CHECK_KEY = "sb3-preferences-connection-check"
"""a pair key asked about before anything runs: the answer (no such pair) says the server is
there and takes the run's token"""


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not (args.token and args.run):
        sys.exit("give the external run's --run and --token (docs/EXTERNAL.md)")
    if args.rounds < 1:
        sys.exit("give at least one round (--rounds)")
    try:
        ClipConfig(width=args.size, height=args.size)
    except ValueError as err:
        sys.exit(f"--size {args.size}: {err}")
    try:
        # The server, the run and its token, before minutes of rendering and training: a few
        # quick tries, not the client's half minute of retries.
        with Study(args.url, args.token, args.run, retries=2, progress=False) as check:
            check.states([CHECK_KEY])
        with Study(args.url, args.token, args.run, cursor_file=args.cursor_file or None,
                   progress=args.progress) as study:
            return run(args, study)
    except StudyError as err:  # refused (a 4xx), unreachable, or the run is over
        sys.exit(f"sepoa server {args.url}, run {args.run}: {err}")
    except (ValueError, TimeoutError) as err:  # a cursor file of another run; answers late
        sys.exit(str(err))


def run(args: Args, study: Study) -> int:
    """The agent, its rounds of asking through `study` and training, and the summary."""
    # MuJoCo reads its GL backend once, at import (by gym.make): EGL, else OSMesa, as the app's
    # worker chooses it.
    choose_backend(lambda line: print(line, flush=True))
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)  # the reward model's initial weights
    rng = np.random.default_rng(args.seed)
    steps = Steps()
    base = gym.make(args.env_id)
    obs_dim, action_dim = base.observation_space.shape[0], base.action_space.shape[0]  # type: ignore[index]
    preferences = Preferences(obs_dim, action_dim, args.net_width, args.seed)
    env = LearnedReward(base, steps, preferences)
    film = Film(args.env_id, args.size, args.seed)
    agent = SAC("MlpPolicy", env, seed=args.seed, learning_starts=args.first_steps,
                batch_size=args.batch_size,
                buffer_size=max(100_000, args.first_steps + args.rounds * args.steps_per_round),
                policy_kwargs={"net_arch": [args.net_width, args.net_width]}, verbose=0)
    # A logger with no outputs: SB3's own makes an empty /tmp/SB3-<time> folder at every learn().
    agent.set_logger(Logger(folder=None, output_formats=[]))
    agent.learn(args.first_steps)  # random actions, no updates yet
    preferences.standardise_by(np.stack(steps.obs_action))
    asked = used = 0
    started = time.monotonic()
    for round_ in range(args.rounds):
        pushed, said = ask_round(study, steps, film, preferences, args, round_, rng)
        asked, used = asked + pushed, used + said
        fit = preferences.train()
        relabel(agent, preferences)
        print(f"round {round_}: {used} answers so far; reward model "
              f"{ {k: round(v, 3) for k, v in fit.items()} }", flush=True)
        since = len(steps)
        agent.learn(args.steps_per_round, reset_num_timesteps=False)
        per_step = np.mean(steps.true_reward[since:])
        print(f"round {round_}: SAC at {agent._n_updates} updates; true reward per step "
              f"since the answers {per_step:.3f}", flush=True)
    film.env.close()
    env.close()
    summary = {"pairs_asked": asked, "answers_used": used,
               "reward_model": {k: float(v) for k, v in fit.items()},
               "held_out": held_out_order(steps, since, args, rng, preferences),
               "sac_updates": int(agent._n_updates), "env_steps": len(steps),
               "replay_reward_vs_true": replay_reward_vs_true(agent, steps),
               "true_returns": [round(r, 2) for r in env.true_returns],
               "seconds": round(time.monotonic() - started, 1)}
    print(json.dumps(summary), flush=True)
    if args.summary:
        Path(args.summary).write_text(json.dumps(summary, indent=2))
    return 0


def replay_reward_vs_true(agent: SAC, steps: Steps) -> float:
    """The correlation of the rewards SAC's replay buffer holds (the learned ones) with the
    environment's own rewards for the same steps."""
    buffer = agent.replay_buffer
    assert buffer is not None and not buffer.full and buffer.pos == len(steps)
    return float(np.corrcoef(buffer.rewards[:buffer.pos, 0], steps.true_reward)[0, 1])


def held_out_order(steps: Steps, since: int, args: Args, rng: np.random.Generator,
                   preferences: Preferences) -> dict[str, float]:
    """How the learned reward orders segments of the last phase (asked of nobody) against their
    true returns: the share of pairs it puts in the true order (0.5 is chance), and the rank
    correlation of the two returns."""
    starts = np.unique(steps.starts(args.segment, rng, args.held_out, since=since))
    true = np.array([steps.true_return(s, args.segment) for s in starts])
    guess = np.array([preferences.reward(steps.segment(s, args.segment)).sum() for s in starts])
    i, j = np.triu_indices(len(starts), k=1)
    decisive = true[i] != true[j]
    agree = (np.sign(true[i] - true[j]) == np.sign(guess[i] - guess[j]))[decisive]
    true_rank, guess_rank = (np.argsort(np.argsort(x)) for x in (true, guess))
    return {"segments": int(len(starts)), "pairs_in_true_order": float(agree.mean()),
            "rank_correlation": float(np.corrcoef(true_rank, guess_rank)[0, 1])}


if __name__ == "__main__":
    sys.exit(main())
