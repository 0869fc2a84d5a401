"""Figures that tests report (failover times ...), printed at the end of the pytest run."""
FIGURES = []


def report(line):
    FIGURES.append(line)
