"""The MJCF models of the tasks (README.md here), installed as the package `envs_mjx.assets`."""
