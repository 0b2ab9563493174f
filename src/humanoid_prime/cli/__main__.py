import sys

from humanoid_prime.cli import main

sys.exit(main())
