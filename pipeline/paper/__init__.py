"""What ``flexdof figures`` and ``flexdof bench`` run: the paper's figures
(``figures``), its four applications (``applications``) and the accuracy-vs-time
benchmark (``bench``).
"""
