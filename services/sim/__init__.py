"""Navigation simulator: the pybullet Husky env, the Dijkstra oracle, SPL and the sim service.

Importing this package registers the Gymnasium ids, so
``gymnasium.make("services.sim:BrainNav-SSSG-v0")`` works without further imports.
"""

from gymnasium.envs.registration import register

MAX_EPISODE_STEPS = 120

register(
    id="BrainNav-SSSG-v0",
    entry_point="services.sim.env:BrainNavEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
    kwargs={"task": "sssg"},
)
register(
    id="BrainNav-VSSG-v0",
    entry_point="services.sim.env:BrainNavEnv",
    max_episode_steps=MAX_EPISODE_STEPS,
    kwargs={"task": "vssg"},
)
