"""Evaluation: metrics, tables, figures and experiment summaries."""
