import sys

from humanoid_prime.virtual.prime import main

sys.exit(main())
