"""Records made from judged runs: statistical process control and yield (spc.py), calibration
certificates (certificate.py, pure core; certificate_pdf.py draws it)."""
