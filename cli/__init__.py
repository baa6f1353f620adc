"""Command-line interface of o3dsoft (installed as o3dsoft.cli)."""
