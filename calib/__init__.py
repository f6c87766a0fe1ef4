"""calib: the physics of the workbench (model, parameters, ingestion, fitting).

``calib`` never imports ``optimize``.
"""
__version__ = "0.1.0"
