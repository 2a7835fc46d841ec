"""Chessboard detection, one module per step of the paper's pipeline (see detector.py for the order)."""
