"""Jobs: the DAG layer (serial or Ray), the attack job and the scene jobs the CLI runs."""
