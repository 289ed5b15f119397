"""Per-episode MCAP logs: writing, reading, scanning and salvaging.

One episode is one MCAP file. ``writer.EpisodeWriter`` writes it, ``reader.EpisodeReader`` / ``read_episode`` read
it back into :class:`recorder.schema.Frame` objects, ``reader.scan_episode`` / ``episode_summary`` /
``count_frames`` inspect it cheaply, and ``recovery.recover`` salvages the complete frames of a recording that was
killed. ``signals.graceful_signals`` turns SIGTERM/SIGINT into an ``Interrupted`` exception so that writers are
closed cleanly (the writer itself installs no signal handler).

Modules, each importing only those above it in this list (import from the module, not from the package):

    layout      what a frame is (its topics), the metadata records, file names, the header library string
    exceptions  CorruptMcapError and the exceptions that decoders raise on damaged bytes
    signals     graceful_signals: SIGTERM/SIGINT -> Interrupted; the critical sections the writer defers them in
    codecs      the JSON array/float codec, the JSON schemas, the protobuf type per topic, depth in mm
    frames      Frame -> serialized messages (FrameEncoder: Foxglove protobuf + JSON) and back (decode_frame)
    writer      EpisodeWriter: start -> add* -> finish (or abort), ``*.mcap.partial`` -> rename
    reader      footer/summary/data CRC validation, EpisodeReader, read_episode, count_frames, scan_episode,
                episode_summary
    recovery    recover: salvage the complete frames of a ``*.mcap.partial``
    bench       benchmark_writer: the chunking/compression measurement
    cli         ``python -m recorder.mcap.cli {recover FILE | summary FILE | bench}``
"""
