"""``python -m usdforest``: the ``usdforest`` command, for a Python whose scripts folder is not
on PATH (a venv that is not activated, ``pip install --user``)."""

from usdforest.entry import main

if __name__ == "__main__":
    main()
