"""The results page (``results/README.md``) from finished sweeps.

Figure 3 beside the paper and the robustness study.

May import: everything below ``cli``.
"""
