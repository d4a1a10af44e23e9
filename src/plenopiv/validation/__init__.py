"""Validation studies that reproduce the thesis's figures and tables with the project's simulator."""
