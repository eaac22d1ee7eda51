"""drivers - the bus drivers of chcos, one module per bus kind, behind :class:`drivers.base.Driver`.

Drivers are found by kind through :func:`drivers.registry.driver_class`, which reads the
``chcos.drivers`` entry points declared in ``pyproject.toml`` (third parties add their own the same
way).
"""
