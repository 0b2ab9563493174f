import sys

try:
    from humanoid_prime.cli import main
except KeyboardInterrupt:  # Ctrl-C while the command line itself loads
    print("prime: interrupted", file=sys.stderr)
    sys.exit(130)

sys.exit(main())
