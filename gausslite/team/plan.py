"""The robots of a team mission: each one's name, sequence and task (:class:`AgentPlan`), and each one's frames
loaded as its agent replays them (:func:`load_eval_frames`): the ground truth its own and the team's maps are scored
on."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Dict, List

from gausslite.datasets import load_dataset

if TYPE_CHECKING:
    from gausslite.mission.config import AgentConfig


@dataclass
class AgentPlan:
    """One robot of a team mission: ``name`` (also its agent id), the ``dataset`` folder it replays, its task
    (``task_id`` in the scene's ``tasks.json``, ``task`` its text) and ``address`` (``host:port`` of its agent
    service, once one runs; empty otherwise)."""

    name: str
    dataset: str
    task_id: str
    task: str
    address: str = ""


def load_eval_frames(plans: List[AgentPlan], agent_cfg: AgentConfig) -> Dict[str, tuple]:
    """Agent id → ``(dataset, frames)``: each agent's sequence loaded as its agent replays it (``agent_cfg``: the
    typed :class:`gausslite.mission.config.AgentConfig`; downscale, max_frames, stride, bag options), every frame in
    memory (world frame, the dataset's poses).

    Raises:
        FileNotFoundError, ValueError: a sequence the loaders cannot read (:func:`gausslite.datasets.load_dataset`).
    """
    eval_frames = {}
    for p in plans:
        ds = load_dataset(p.dataset, downscale=agent_cfg.downscale, max_frames=agent_cfg.max_frames,
                          stride=agent_cfg.stride, bag=agent_cfg.bag)
        eval_frames[p.name] = (ds, [ds[i] for i in range(len(ds))])
    return eval_frames
