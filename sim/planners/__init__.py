"""Model-based planners that drive the crowd world without learning.

* :mod:`sim.planners.dwa` — the Dynamic Window Approach (Fox et al. 1997) on the robot's own depth images and
  odometry: the paper's model-based baseline.
* :mod:`sim.planners.topomap` — a generalized-Voronoi-graph topological map of a scene's occupancy grid,
  planning
  on it and a waypoint follower: the paper's long-horizon setting (§IV-C), where a local controller follows
      the
  graph's waypoints.
"""
