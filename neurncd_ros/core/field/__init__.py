"""Embedding-NeRF: fields, samplers, renderer, losses, keyframe buffer and mapper.

Layout (nerfstudio-like): ``encoding`` (positional encoding, SH, tri-planes),
``fields`` (F(x, d) = (c, e, sigma): the paper's MLP and the tri-plane field),
``samplers`` (stratified, importance, depth-guided, AABB near/far),
``renderer`` (quadrature weights, compositing), ``losses`` (L_p, L_e = KL,
depth, free space, entropy), ``models`` (the two backends), ``keyframes``
(bounded buffer), ``mapper`` (``MapperConfig``, ``Mapper``: the API the node
and the offline pipeline use).
"""
