"""Research tools: diagnostics of trained runs and of the tasks, beside the product's scripts in ``zoo_scripts/``.

They answer questions the results raise (who acted, which level fails, what the demonstrations teach, what the higher
level learns from its labels, how fast the tasks are) and are documented in the documentation's research tools page
(``docs/guide/research_tools.rst``); the package and the product's scripts never import them. Each runs as
``python zoo_scripts/research/<tool>.py``.
"""
