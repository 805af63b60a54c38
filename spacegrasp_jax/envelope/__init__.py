"""What a capture is and where it may go: the scenario, its perturbations, the metrics of a run,
the capture criteria, statistics of success rates and the plausibility of inputs and results.
A module here imports only ``core`` and modules here."""
