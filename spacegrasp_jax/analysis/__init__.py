"""What is made of runs: stability margins, the linear analysis, the worst-case search, the
sensitivity of an outcome to the perturbations, gain sweeps, figures, films and the export of gains for flight software. A module here may import
every layer below."""
