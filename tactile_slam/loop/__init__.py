"""Loop closure: coverage set, curvature features, candidate retrieval, verification."""
