"""The pybullet crowd world: scenes, social-force pedestrians, articulated humans, robot, cameras, env.

Importing ``sim`` registers the gymnasium environment ``icrowdnav/CrowdNav-v0``::

    import gymnasium, sim
    env = gymnasium.make("icrowdnav/CrowdNav-v0", scene="office_lobby", density=0.1)
"""

import gymnasium

ENV_ID = "icrowdnav/CrowdNav-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="sim.env:CrowdNavEnv")
