"""The agents by name (`AGENTS`): each an algorithm family, declared in one module (`ddpg`), and what it
observes (`family.Agent`). A new algorithm is a module declaring its `family.Family` and an entry here."""

from __future__ import annotations

from bidal_jax.agents import ddpg
from bidal_jax.agents.family import Agent, Family, Loss, Step

AGENTS: dict[str, Agent] = {
    "proprio_baseline": Agent(ddpg.DDPG, uses_image=False, uses_proprio=True),
    "visual_baseline": Agent(ddpg.DDPG, uses_image=True, uses_proprio=False),
    "multimodal_baseline": Agent(ddpg.DDPG, uses_image=True, uses_proprio=True),
    "visual_bidal": Agent(ddpg.BIDAL, uses_image=True, uses_proprio=False),
    "multimodal_bidal": Agent(ddpg.BIDAL, uses_image=True, uses_proprio=True),
    # multimodal_bidal at λ = 0: the forward and inverse losses without their reward (an ablation, no paper agent)
    "multimodal_bidal_no_ri": Agent(ddpg.BIDAL_NO_REWARD, uses_image=True, uses_proprio=True),
}


def get(name: str) -> Agent:
    """The agent registered as `name`; ValueError naming the valid ones."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; valid agents: {', '.join(AGENTS)}")
    return AGENTS[name]


__all__ = ["AGENTS", "Agent", "Family", "Loss", "Step", "get"]
