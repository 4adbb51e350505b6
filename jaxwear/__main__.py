import sys

from jaxwear.cli import main

sys.exit(main())
