"""One-off research scripts kept so their published tables can be reproduced; not part of the installed package
(run from the repository root: ``./dev python -m scripts.NAME``)."""
