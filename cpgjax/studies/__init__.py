"""The studies, above the engine (``cpgjax.ablation``): the paper's five (``registry``) and the transfer study
(``transfer``), what they report (``stats``, ``figures``, ``video``, the web viewer ``viewer``) and the launcher of a
study's processes (``launch``)."""
