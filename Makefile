.PHONY: setup run test

setup:
	scripts/setup.sh

run: setup
	.venv/bin/hrc serve

test:
	scripts/test.sh
