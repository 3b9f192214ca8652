"""What a study is, below the engine that runs it (``cpgjax.ablation``): its specification (``spec``), its files
(``files``: checkpoint, trial table, recording, metadata) and the robot's scene in the recording (``scene``). The
paper's studies, their reports and the launcher are ``cpgjax.studies``."""
