"""Embedding-NeRF: fields, samplers, renderer, losses, backends, keyframe buffer and mapper.

Layout (nerfstudio-like): ``encoding`` (positional encoding, SH, tri-planes),
``fields`` (F(x, d) = (c, e, sigma): the paper's MLP and the tri-plane field),
``samplers`` (stratified, importance, depth-guided, AABB near/far),
``renderer`` (quadrature weights, compositing), ``losses`` (L_p, L_e = KL,
depth, free space, entropy), ``backends`` (the ``FieldModel`` interface, a
registry, one module per backend with its config section: ``fast``,
``reference``), ``keyframes`` (bounded buffer), ``scenebox`` (the growing
scene AABB), ``mapper`` (``MapperConfig``, ``Mapper``: the API the nodes and
the offline pipeline use).
"""
