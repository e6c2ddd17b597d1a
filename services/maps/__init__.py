"""Planning on occupancy grids: the corridor planner, which composes the wall cover (`services.ellipsoids.grid_cover`)
with the planner core, fitting only the tiles the query comes near."""
