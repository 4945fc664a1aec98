"""``python -m sb3_dipper.zoo``: the ``sb3-dipper-zoo`` command."""

from sb3_dipper.zoo import main

main()
