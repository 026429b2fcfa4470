"""The one generator of synthetic bodies, poses, hands and facial expressions every companion draws from."""
