# DetMatch command-line tools (training, evaluation, data) on CPU.
# Build: docker build -t detmatch .   Run: docker run --rm -v "$PWD/data:/data" detmatch synth --out /data/synth --frames 100
FROM python:3.11-slim
WORKDIR /opt/detmatch
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml README.md ./
COPY detmatch ./detmatch
RUN pip install --no-cache-dir '.[train,serve]'
ENTRYPOINT ["detmatch"]
