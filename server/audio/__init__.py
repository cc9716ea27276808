"""Speech → visemes and lip/jaw FAPs by linear-predictive analysis (Kshirsagar & Magnenat-Thalmann).

- ``io``: decode, validate, downmix and resample audio (batch and streaming).
- ``lpc``: pre-emphasis, Hamming frames, autocorrelation, Levinson–Durbin reflection coefficients,
  frame energy and zero-crossing rate (pure functions).
- ``classify``: the 12-10-5 vowel network (inference in NumPy; weights in ``vowel_net.npz``);
  ``generate`` / ``train``: its espeak-ng training material and ``python -m
  facecast.server.audio.train``.
- ``visemes``: energy/ZCR rules, median filtering, Cohen–Massaro coarticulation, mouth shapes from
  ``facecast.server.mpeg4.VISEMES``; ``pipeline.lipsync``: the whole batch chain.
- ``driver.load``: audio file → ``Animation`` (``facecast render speech.wav``);
  ``live.AudioLiveDriver``: PCM chunks → face states (live sessions).
"""
