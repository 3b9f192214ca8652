"""Studies: their specification, the paper's five studies, checkpoints and result files, and figures. The engine that
runs them is ``cpgjax.ablation``."""
