"""``python -m saml_ros.demo``."""

from saml_ros.demo.cli import main

raise SystemExit(main())
