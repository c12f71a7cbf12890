"""Discovery: geometric segmentation, feature modulation, Markov clustering, labels, metrics."""
