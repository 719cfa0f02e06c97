.PHONY: setup run test

setup:
	scripts/setup.sh

run: setup
	.venv/bin/hrc --help

test:
	scripts/test.sh
