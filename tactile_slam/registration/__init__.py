"""Pairwise registration: NormalFlow and the ICP / FPFH baselines."""
