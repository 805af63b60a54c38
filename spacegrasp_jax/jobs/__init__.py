"""Runs on the host: compilation and the store of compiled programs, single runs and their
records, batches over devices and hosts, campaigns, run files, the failures' anatomy and the
paper's reference numbers. A module here imports only the layers below and modules here."""
