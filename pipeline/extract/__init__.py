"""skidbench.pipeline.extract"""
