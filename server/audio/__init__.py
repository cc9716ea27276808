"""Speech → visemes and lip/jaw FAPs by linear-predictive analysis (Kshirsagar & Magnenat-Thalmann).

- ``io``: decode, validate, downmix and resample audio (batch and streaming).
- ``lpc``: pre-emphasis, Hamming frames, autocorrelation, Levinson–Durbin reflection coefficients,
  frame energy and zero-crossing rate (pure functions).
- ``classify``: the frame network (level-independent LPC features stacked over 80 ms back and
  30 ms ahead → ten visual classes; weights in ``frame_net.npz``, trained on real speech by
  ``bench/lipsync/frames.py``) and the source's 12-10-5 vowel network (``vowel_net.npz``;
  ``generate`` / ``train``: its espeak-ng material and ``python -m facecast.server.audio.train``).
- ``visemes``: calibration (from the file, or the source's room noise + loud /a/), median
  filtering, Cohen–Massaro coarticulation, mouth shapes from ``facecast.server.mpeg4.VISEMES``;
  ``pipeline.lipsync``: the whole batch chain; ``align.align_text``: the same with a transcript;
  ``cues``: segments and Rhubarb Lip Sync's mouth-cue formats.
- ``driver.load``: audio file → ``Animation`` (``facecast render speech.wav``);
  ``live.AudioLiveDriver``: PCM chunks → face states (live sessions).
"""
