"""``python -m humanoid_prime`` and the ``prime`` script: the command line (``humanoid_prime.cli``), with Ctrl-C
watched (``humanoid_prime.interrupts``) from before it loads: one line and exit 130 at any moment of its start-up."""

import sys


def prime() -> int:
    interrupts = None
    try:
        from humanoid_prime.interrupts import Interrupts

        interrupts = Interrupts()
        from humanoid_prime.cli import main

        return main(interrupts=interrupts)
    except KeyboardInterrupt:  # while the command line loads, before main() knows the command
        print("prime: interrupted", file=sys.stderr)
        return 130
    finally:
        if interrupts is not None:
            interrupts.close()


if __name__ == "__main__":
    sys.exit(prime())
