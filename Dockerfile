# DetMatch: the command-line tools (data, training, evaluation, export) and the labeling service.
# Build: docker build -t detmatch .
# Data:  docker run --rm -v "$PWD/data:/data" detmatch synth --out /data/synth --frames 100
# Serve: docker run --rm -p 50051:50051 -v "$PWD/models:/models" -v "$PWD/store:/store" \
#            detmatch serve --repository /models --store /store --port 50051
FROM python:3.11-slim
WORKDIR /opt/detmatch
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml setup.py README.md ./
COPY detmatch ./detmatch
COPY export ./export
COPY serving ./serving
COPY protos ./protos
# setup.py's build step generates the gRPC stubs from protos/ into the installed package.
RUN pip install --no-cache-dir '.[train,serve]'
ENTRYPOINT ["detmatch"]
