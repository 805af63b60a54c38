"""A listener that keeps the labels of the compiles the package makes."""

from __future__ import annotations


class CompileLabels:
    """A ``compilation.listening`` listener that keeps the labels of the compiles it hears."""

    def __init__(self):
        self.labels = []

    def before(self, label, key):
        self.labels.append(label)

    def after(self, label, key, seconds):
        pass
