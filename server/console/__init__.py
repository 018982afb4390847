"""The operator's console: live push, the viser 3D scene, alarms, the pages' includes, and their
routes."""
