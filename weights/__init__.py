"""The shipped TorchScript model and its card (installed as o3dsoft.weights)."""
