"""The NeRF components in pure torch: encodings, fields, sampling, quadrature, the volume renderer, the
occupancy grid and analytic fields. Nothing here imports the rest of nerfexp, Lightning or Hydra."""
