"""CLI subcommands, one module each; every module exposes ``COMMANDS`` (a list of click
commands).  Keep heavy imports (torch, jax, ray, scipy) inside the command functions so
``artdata --help`` stays fast and optional extras stay optional."""
