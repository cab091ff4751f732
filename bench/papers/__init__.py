"""Figures of the papers mvreg implements, reproduced on synthetic data.

- :mod:`.paper000_fig2` -- REG-ADMM convergence and rho sensitivity (paper 000, Fig. 2);
- :mod:`.paper000_fig3` -- C-ADMM and the spectral relaxation on the paper's networks (Fig. 3);
- :mod:`.paper001_fig1` -- solvers' rotation error and time on two overlap graphs (paper 001, Fig. 1).
"""
