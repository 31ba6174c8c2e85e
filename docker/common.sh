# Sourced by the docker/ scripts and scripts/test-docker: which docker client to use.
# Debian's docker.io client (20.10, /usr/bin/docker) builds with the engine's own BuildKit;
# a newer client elsewhere on the PATH may want a buildx plugin that is not installed.
if [ -z "${DOCKER:-}" ]; then
  if [ -x /usr/bin/docker ]; then DOCKER=/usr/bin/docker; else DOCKER=docker; fi
fi
export DOCKER
