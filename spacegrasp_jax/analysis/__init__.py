"""What is made of runs: stability margins, the linear analysis, the worst-case search, gain
sweeps, figures, films and the export of gains for flight software. A module here may import
every layer below."""
