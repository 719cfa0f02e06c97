.PHONY: setup run test docs

setup:
	scripts/setup.sh

run: setup
	.venv/bin/hrc serve

test:
	scripts/test.sh

docs: setup
	NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict
