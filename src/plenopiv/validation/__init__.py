"""Validation studies: the thesis's figures and tables reproduced with the project's simulator."""
