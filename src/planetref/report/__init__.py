"""Figures and reports (matplotlib, Agg backend); importing this package has no side effects."""
