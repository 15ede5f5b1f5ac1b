"""Allow ``python -m aerialmtl``."""

from aerialmtl.cli import main

if __name__ == "__main__":
    main()
