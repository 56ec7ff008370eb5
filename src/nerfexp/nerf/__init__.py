"""The NeRF components in pure torch: encodings, fields, sampling, quadrature, the volume renderer and the
occupancy grid. Nothing here imports the rest of nerfexp, Lightning or Hydra."""
