"""The closed loop: the laws (``control``), the realism and its stages, and ``simulate``, which
chains them with the integrator. A module here imports only ``core``, ``envelope`` and modules
here."""
