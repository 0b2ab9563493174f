import sys

from humanoid_prime.emulation.virtual_prime import main

sys.exit(main())
