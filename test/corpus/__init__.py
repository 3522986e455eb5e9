"""Generated bad-input corpora for the tests (DICOM files, messages)."""
