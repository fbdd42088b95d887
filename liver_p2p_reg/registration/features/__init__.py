"""Point features: FPFH (Open3D) and the learned matcher, behind one FeatureProvider interface."""
