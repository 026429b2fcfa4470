"""Pose correctives shared by every identity backend (paper 000 §3.5.2, issue 40)."""
