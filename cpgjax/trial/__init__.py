"""The paper's trial, backend-neutral: the 8 optimized parameters, the trial protocol (transition, steady phase,
per-tick sums, summary) and the trial figures J, CoT and the context (eqs. 9-11)."""
